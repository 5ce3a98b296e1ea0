"""compare's report lists a scanner of many beams in blocks of neighbouring beams; the JSON keeps every beam.

On the Intel log (180 beams) and the room's planar-360 scanner the report's "By beam" section held one
row per beam (180 and 360 rows): a wall of numbers nobody reads.
"""

import json

import numpy as np

from mi_lidar.core.patterns import get_pattern
from mi_lidar.loop import compare
from mi_lidar.loop.compare import beam_blocks, breakdown, metrics
from mi_lidar.scene.simulation import simulate
from tests.core.test_strict_json import strict_load

from .helpers import room, street
from .test_report_order import table


def test_a_planar_scan_is_listed_in_blocks_of_beams_named_by_their_bearings(tmp_path):
    scene, model, poses = room(2)
    log = simulate(scene, poses=poses, model=model, seed=1)
    result = compare(log, scene, model, out=tmp_path)
    saved = json.loads((tmp_path / "comparison.json").read_text())
    assert len(saved["breakdowns"]["beam"]) == 360  # every beam stays in the JSON
    blocks = saved["beam_blocks"]
    assert len(blocks) == 12 and {b["beams"] for b in blocks} == {30}
    assert blocks[0]["group"].startswith("beams 0-29 (") and blocks[-1]["group"].startswith("beams 330-359 (")
    assert sum(b["rays"] for b in blocks) == result.headline["rays"]
    section = (tmp_path / "report.md").read_text().split("### By beam")[1].split("###")[0]
    rows = [line for line in section.splitlines() if line.startswith("| beams ")]
    assert len(rows) == 12 and "| beam 0" not in section
    assert "360 beams in 12 rows of 30 neighbouring beams" in section and "breakdowns.beam" in section


def test_a_block_scores_all_the_rays_of_its_beams():
    t = table(np.linspace(-179, 179, 600))  # 50 beams whose azimuth changes from firing to firing (spinning)
    t.beam = np.arange(600) % 50
    t.ll = -np.linspace(0.0, 3.0, 600)
    rows = beam_blocks(t, blocks=12)
    assert [r["group"] for r in rows[:2]] == ["beams 0-4", "beams 5-9"]  # no bearing: the beams turn
    assert len(rows) == 10 and all(r["beams"] == 5 for r in rows)
    pooled = metrics(t, t.beam < 5)
    assert np.isclose(rows[0]["nll"], pooled["nll"]) and rows[0]["rays"] == pooled["rays"] == 60
    assert np.isclose(sum(r["excess_nll"] for r in rows), sum(r["excess_nll"] for r in breakdown(t, "beam")))


def test_a_few_beams_are_listed_one_per_row(tmp_path):
    scene, model, poses = street(1)
    log = simulate(scene, get_pattern("vlp16", n_firings=90), poses=poses, model=model, seed=3)
    result = compare(log, scene, model, out=tmp_path)
    saved = strict_load((tmp_path / "comparison.json").read_text())  # strict JSON: it held NaN
    assert result.beam_blocks == [] and "beam_blocks" not in saved
    # the rays that met no element (the sky) have no range error and no hit to score: null, not NaN
    sky = next(row for row in saved["breakdowns"]["range"] if row["group"] == "none")
    assert sky["rays"] > 0 and sky["range_error_median"] is None and sky["f1"] is None, sky
    section = (tmp_path / "report.md").read_text().split("### By beam")[1].split("###")[0]
    assert len([line for line in section.splitlines() if line.startswith("| beam ")]) == 16


def test_block_bearings_keep_the_beam_spacing_and_never_read_minus_zero():
    """Freiburg 079 (360 beams over 180 deg) read 'beams 30-59 (-75..-60 deg)', 'beams 60-89 (-60..-46 deg)' and
    'beams 150-179 (-15..-0 deg)'."""
    t = table(np.zeros(720))
    t.beam = np.arange(720) % 360
    t.azimuth = -90.0 + 0.5 * t.beam
    names = [r["group"] for r in beam_blocks(t)]
    assert names[1] == "beams 30-59 (-75.0..-60.5 deg)" and names[5] == "beams 150-179 (-15.0..-0.5 deg)"
    t.beam = np.arange(720) % 180
    t.azimuth = -89.3 + 1.0 * t.beam  # 1 deg beams: whole degrees; beam 89 at -0.3 deg
    names = [r["group"] for r in beam_blocks(t)]
    assert names[5] == "beams 75-89 (-14..+0 deg)" and names[6] == "beams 90-104 (+1..+15 deg)"
