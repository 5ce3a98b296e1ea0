"""compare and diagnose refuse a log from another sensor than the scene's, unless forced."""

import re

import numpy as np
import pytest
from typer.testing import CliRunner

import mi_lidar
from mi_lidar.cli import app
from mi_lidar.core.patterns import get_pattern
from mi_lidar.scene.sensor_check import SensorSummary, fields_of_view, mismatches

from ..conftest import SCENES

runner = CliRunner()


@pytest.mark.parametrize(
    "name,firings,vertical,horizontal",
    [("vlp16", 8, 30.0, 360.0), ("vlp16", 900, 30.0, 360.0), ("planar-180", 1, 0.0, 180.0), ("raster", None, 25, 120)],
)
def test_fields_of_view_of_patterns(name, firings, vertical, horizontal):
    pattern = get_pattern(name, n_firings=firings) if firings and name == "vlp16" else get_pattern(name)
    v, h = fields_of_view(pattern.directions())
    assert v == pytest.approx(vertical, abs=0.6) and h == pytest.approx(horizontal, abs=1.5)


def test_mismatches_name_each_difference():
    vlp16 = SensorSummary("vlp16", 16, 30.0, 360.0, 100.0)
    assert mismatches(SensorSummary("log", 16, 29.5, 352.0, 60.0), vlp16) == []
    found = mismatches(SensorSummary("log", 180, 0.0, 180.0, 20_000.0), vlp16)
    assert found == [
        "180 beams vs 16",
        "vertical field of view 0.0 deg vs 30.0",
        "horizontal field of view 180 deg vs 360",
        "returns up to 20000.0 m (99th percentile) vs a maximum range of 100.0 m",
    ]
    assert mismatches(SensorSummary("log", 16, 30.0, 360.0, 50.0), vlp16, range_unit="mm") == [
        "ranges in 'mm', not metres"
    ]


@pytest.fixture(scope="module")
def planar_log(tmp_path_factory):
    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    return mi_lidar.simulate(scene, seed=1).save(tmp_path_factory.mktemp("planar") / "room.npz")


@pytest.mark.parametrize("verb", ["compare", "diagnose", "fit-sensor"])
def test_planar_log_in_the_offroad_scene_is_refused_unless_forced(tmp_path, planar_log, verb):
    out = str(tmp_path / ("out.npz" if verb == "fit-sensor" else "out"))
    args = [verb, str(planar_log), str(SCENES / "offroad.xml"), "--out", out]
    refused = runner.invoke(app, args)
    text = " ".join(refused.output.split())
    assert refused.exit_code == 2, text
    assert f"error: {planar_log}: the log's sensor (planar-360" in text  # it did not name the file
    assert "planar-360: 360 beams" in text and "vlp16: 16 beams" in text and "360 beams vs 16" in text
    # the log's range is its 99th percentile: 'returns up to 13.5 m' read as the farthest return (Intel's is 25.4 m)
    assert "99 % of returns within " in text and "returns up to" not in text
    assert "--force" in text and "Traceback" not in text
    if verb == "compare":
        forced = runner.invoke(app, [*args, "--force"])
        assert forced.exit_code == 0, forced.output
        assert np.isfinite(float(forced.output.split("NLL ")[1].split()[0]))


def test_the_mismatch_names_the_log_file_when_it_was_read_from_one(planar_log):
    """The message began "the log's sensor" whichever file the log came from."""
    from mi_lidar.core.errors import SensorMismatchError
    from mi_lidar.io.dispatch import read_any
    from mi_lidar.scene.sensor_check import check_log_sensor

    scene = mi_lidar.load_scene(SCENES / "offroad.xml")
    log = read_any(planar_log)
    assert log.source == str(planar_log) and log.scan(0).source == str(planar_log)
    with pytest.raises(SensorMismatchError, match=rf"^{re.escape(str(planar_log))}: the log's sensor \(planar-360"):
        check_log_sensor(log, scene)
    log.source = None  # made in memory
    with pytest.raises(SensorMismatchError, match=r"^the log's sensor \(planar-360"):
        check_log_sensor(log, scene)
