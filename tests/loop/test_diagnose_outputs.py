"""diagnose hands back what it found: an HTML report and the scene XML with the model's effects."""

import json

import mitsuba as mi
import numpy as np

from mi_lidar.scene import load_scene, scene_sensor_model
from mi_lidar.scene.files import scene_with_effects
from tests.terminal import assert_whole, invoke_at_80

from ..conftest import SCENES
from .helpers import diagnose_hidden_bias, hidden_log, room


def test_diagnose_writes_html_and_the_scene_with_the_found_effect(tmp_path, monkeypatch):
    """A hidden 5 cm range bias is found; the page shows its before/after figure and the samples' realism beside the
    NLL; out/scene.xml loads from another folder and carries it (seeded; the bias refits within 1 cm)."""
    result, out = diagnose_hidden_bias(tmp_path, "range_bias", "outliers")
    assert result.exit_code == 0, result.stdout
    report = json.loads((out / "diagnosis.json").read_text())
    assert_whole(result.stdout, f"{report['nll_before']:.4f}", f"{report['nll_after']:.4f}")
    page = (tmp_path / "d" / "diagnosis.html").read_text()
    assert "range_bias" in page and "realism of samples" in page and 'src="before_after_1.png"' in page
    # the ranking's last column read 'train LR' (a learning rate?) with no word of what it is
    assert "<th>training LR statistic</th>" in page and "twice the log-likelihood gain" in page
    assert (tmp_path / "d" / "before_after_1.png").stat().st_size > 10_000
    realism = json.loads((tmp_path / "d" / "diagnosis.json").read_text())["realism"]
    assert [r["model"] for r in realism] == ["given model", "+ range_bias", "final model"]
    assert realism[2]["nll"] < realism[0]["nll"] and realism[1]["warning"] == ""
    monkeypatch.chdir(tmp_path)  # the copy's file references are absolute
    found, _ = scene_sensor_model(load_scene(tmp_path / "d" / "scene.xml"))
    bias = [e for e in found.effects if e.name == "range_bias"]
    assert bias and abs(float(np.mean(np.asarray(bias[0].params["bias"]))) - 0.05) < 0.01


def test_scene_with_effects_replaces_an_existing_effects_string(tmp_path):
    text = (SCENES / "indoor_planar.xml").read_text()
    first = scene_with_effects(SCENES / "indoor_planar.xml", "range_bias(bias=0.02)", tmp_path / "a.xml")
    second = scene_with_effects(first, "outliers(p_near=0.01)", tmp_path / "b.xml")
    out = second.read_text()
    assert out.count('name="effects"') == 1 and "outliers(p_near=0.01)" in out and "range_bias" not in out
    assert out.count("<integrator") == text.count("<integrator")
    model, _ = scene_sensor_model(mi.load_file(str(second)))
    assert [e.name for e in model.effects] == ["outliers"]


def test_a_joined_learned_density_is_saved_and_referenced_by_the_written_scene(tmp_path, monkeypatch):
    """Returns of the independent street arrive late by an exponential delay (no catalog law is skewed): NP-Reg
    beats the model with the effects that spread returns and replaces it; out/scene.xml references its saved
    tables and carries no effect."""
    from mi_lidar.core.densities import NPRegDensity
    from mi_lidar.core.log import Log

    from ..hidden.street import Hidden, scene_xml, street_log

    (tmp_path / "street.xml").write_text(scene_xml())
    Log(**street_log(Hidden(walk=0.03), sweeps=4), sensor={"name": "street"}).save(tmp_path / "walk.npz")
    arguments = ["diagnose", str(tmp_path / "walk.npz"), str(tmp_path / "street.xml"), "--out", str(tmp_path / "d")]
    for name in ("range_noise", "outliers", "range_bias", "np_reg"):
        arguments += ["--candidate", name]
    result = invoke_at_80(arguments)
    assert result.exit_code == 0, result.stdout
    report = json.loads((tmp_path / "d" / "diagnosis.json").read_text())
    learned = report["rounds"][-1][0]
    assert learned["name"] == "np_reg" and learned["status"] == "joined", learned
    assert report["selected"] == ["np_reg"]
    assert (tmp_path / "d" / "np_reg.npz").is_file()
    monkeypatch.chdir(tmp_path / "d")
    found, _ = scene_sensor_model(load_scene(tmp_path / "d" / "scene.xml"))
    assert isinstance(found.density, NPRegDensity) and found.effects == []
    # the scene names its tables relative to itself (it named them by their absolute path): the folder moves whole
    monkeypatch.chdir(tmp_path)
    (tmp_path / "d").rename(tmp_path / "moved")
    found, _ = scene_sensor_model(mi.load_file(str(tmp_path / "moved" / "scene.xml")))
    assert isinstance(found.density, NPRegDensity)


def test_the_copy_of_a_scene_finds_the_density_tables_named_relative_to_the_source(tmp_path):
    """A scene diagnose wrote names its density's tables relative to itself; a copy written elsewhere (the next
    diagnose's scene.xml) kept the relative name and looked for the tables beside the copy."""
    from mi_lidar.core.densities import NPRegDensity
    from mi_lidar.core.densities.tables import StateGrid

    grid = StateGrid(range_edges=[0.0, 5.0, 1.0e9], incidence_edges=[0.0, 45.0, 90.0], n_labels=2)
    NPRegDensity(grid=grid).save(tmp_path / "first" / "np_reg.npz")
    first = scene_with_effects(
        SCENES / "indoor_planar.xml", "", tmp_path / "first" / "scene.xml", "np_reg(file=np_reg.npz)"
    )
    second = scene_with_effects(first, "range_bias(bias=0.02)", tmp_path / "second" / "scene.xml")
    model, _ = scene_sensor_model(mi.load_file(str(second)))
    assert isinstance(model.density, NPRegDensity) and [e.name for e in model.effects] == ["range_bias"]


def test_a_scanner_of_many_beams_is_drawn_by_groups_of_neighbouring_beams():
    from mi_lidar.loop.diagnosis_report import _beam_groups

    few = np.repeat(np.arange(16.0), 5)
    assert np.array_equal(_beam_groups(few), few)
    many = np.repeat(np.arange(360.0), 3)
    grouped = _beam_groups(many)
    centres, counts = np.unique(grouped, return_counts=True)
    assert centres.size == 12 and np.all(counts == 90)  # 30 neighbouring beams x 3 rays each
    assert np.all(np.abs(grouped - many) <= 15.0)


def test_a_log_too_short_for_a_learned_density_is_diagnosed_without_it():
    """Two planar scans (the README's room.npz): every training ray is in the fitting subsample, so no ray is
    left to estimate NP-Reg on; the diagnosis runs and says why it left the learned densities out."""
    from mi_lidar.loop import diagnose

    scene, model, poses = room(2)
    log, _ = hidden_log(scene, model, poses, "range_bias(bias=0.05)")
    d = diagnose(log, scene, candidates=["range_bias", "np_reg"], rounds=1)
    assert [c.name for r in d.rounds for c in r] == ["range_bias"]
    assert "learned densities were not tried" in d.summary and "record a longer log (more scans)" in d.summary
    assert "or, from Python, pass mi_lidar.loop.diagnose a smaller max_fit" in d.summary  # no CLI option has it


def test_diagnose_json_on_stdout_parses_with_the_progress_on_stderr(tmp_path, monkeypatch):
    """``diagnose --json | json.load``: stdout carries the ranking only; the progress lines go to stderr."""
    from mi_lidar.cli import progress as progress_module

    monkeypatch.setattr(progress_module, "PLAIN_EVERY_S", 0.0)  # every update prints
    scene, model, poses = room(2)
    log, _ = hidden_log(scene, model, poses, "range_bias(bias=0.05)")
    log.save(tmp_path / "room.npz")
    arguments = ["diagnose", tmp_path / "room.npz", SCENES / "indoor_planar.xml", "--out", tmp_path / "d", "--json"]
    result = invoke_at_80([*arguments, "--candidate", "range_bias"])
    assert result.exit_code == 0, result.output
    assert [row["name"] for row in json.loads(result.stdout)] == ["range_bias"]
    assert "diagnose: done (" in result.stderr


def test_diagnose_prints_its_verdict_without_markdown_asterisks(tmp_path):
    """The verdict is written in the reports' Markdown (``**range_bias**``): the terminal shows the name (bold on a
    terminal, plain in a log), not the asterisks."""
    scene, model, poses = room(2)
    log, _ = hidden_log(scene, model, poses, "range_bias(bias=0.05)")
    log.save(tmp_path / "room.npz")
    arguments = ["diagnose", tmp_path / "room.npz", SCENES / "indoor_planar.xml", "--out", tmp_path / "d"]
    result = invoke_at_80([*arguments, "--candidate", "range_bias"])
    assert result.exit_code == 0, result.output
    assert "The model is missing range_bias" in " ".join(result.stdout.split()) and "**" not in result.stdout


def test_a_dimension_with_one_group_is_reported_as_not_testable_not_as_chi2_zero():
    """A scene of one label (or a planar scanner's one elevation) leaves one group: its row said chi2 0.0, dof 0,
    p 1, 'no', as if tested and clean."""
    from mi_lidar.loop.diagnosis_report import structure_row
    from mi_lidar.loop.residuals import residual_structure

    rng = np.random.default_rng(0)
    n = 2000
    nominal = rng.uniform(2.0, 20.0, n)
    measured, simulated = nominal + rng.normal(0.0, 0.02, n), nominal + rng.normal(0.0, 0.02, n)
    hit = np.ones(n, bool)
    found = residual_structure({"label": np.zeros(n), "range": nominal}, nominal, measured, hit, simulated, hit)
    rows = {(s.dimension, s.channel): structure_row(s) for s in found}
    assert rows[("label", "range")].endswith("| - | - | - | - | not testable (fewer than 2 groups of 30 rays) |")
    ranges = rows[("range", "range")].split("|")
    assert ranges[4].strip() == "11" and ranges[7].strip() == "no", ranges  # 12 groups: tested, and clean


def test_the_structure_table_gives_departures_in_cm_and_points_as_the_verdict_does():
    """The table's 'largest departure' read '0.0000 ' for a return rate (no unit) and metres to 4 decimals for
    ranges, while the verdict said 'by 9.8 points RMS': the column is the RMS spread beyond sampling noise."""
    from mi_lidar.loop.diagnosis_report import structure_row
    from mi_lidar.loop.residuals import residual_structure, structure_verdict

    rng = np.random.default_rng(3)
    n = 6000
    nominal = rng.uniform(2.0, 20.0, n)
    measured, simulated = nominal + rng.normal(0.0, 0.02, n), nominal + rng.normal(0.0, 0.02, n)
    hit = rng.random(n) > np.where(nominal > 11.0, 0.2, 0.02)  # beyond 11 m a fifth of the beams drop out
    found = residual_structure({"range": nominal}, nominal, measured, hit, simulated, rng.random(n) > 0.1)
    returns = next(s for s in found if s.channel == "returns")
    ranges = next(s for s in found if s.channel == "range")
    assert returns.flagged and 0.05 < returns.departure < 0.15, returns.departure  # about 10 points
    assert f"| {100 * returns.departure:.2f} points | yes |" in structure_row(returns), structure_row(returns)
    assert f"by {100 * returns.departure:.1f} points RMS" in structure_verdict(found)
    assert structure_row(ranges).endswith(f"| {100 * ranges.departure:.2f} cm | no |"), structure_row(ranges)
