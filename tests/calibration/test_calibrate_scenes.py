"""`mi-lidar calibrate` from the command line on every bundled scene and on a planar CARMEN log.

Each log is simulated here from the scene itself (a few firings, one pose), so the calibrated
scene must load back with the fitted values; the planar log is written as CARMEN ``FLASER``
lines and calibrated with the pattern taken from the log.
"""

import numpy as np
import pytest
from typer.testing import CliRunner

import mi_lidar
from mi_lidar.cli import app
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.patterns import FiringPattern, get_pattern
from mi_lidar.io.carmen import beam_angles
from mi_lidar.scene import scene_lidar_sensor

from ..conftest import SCENES

runner = CliRunner()
SPINNING = ("offroad.xml", "urban_street.xml")  # simulated with 90 firings of their sweep
CARMEN_BEAMS = 91
NO_RETURN = 81.83  # m: the SICK no-return value, written for misses


def calibrate(*args: str):
    result = runner.invoke(app, ["calibrate", *map(str, args)])
    return result, " ".join(result.output.split())


@pytest.mark.parametrize("scene", sorted(p.name for p in SCENES.glob("*.xml")))
def test_every_bundled_scene_calibrates(tmp_path, scene):
    loaded = mi_lidar.load_scene(SCENES / scene)
    sensor = scene_lidar_sensor(loaded)
    pattern = get_pattern(sensor.pattern.name, n_firings=90) if scene in SPINNING else sensor.pattern
    log = mi_lidar.simulate(loaded, pattern, poses=sensor.to_world_matrix[None], seed=4).save(tmp_path / "log.npz")
    result, output = calibrate(log, SCENES / scene, "-p", "elements.*.p_hit", "--out", tmp_path / "out", "--steps", 5)
    assert result.exit_code == 0, output
    assert "held-out NLL" in output
    fitted = np.load(tmp_path / "out" / "parameters.npz")
    table = ElementTable.from_scene(mi_lidar.load_scene(tmp_path / "out" / "scene.xml"))
    assert table.shape_ids == ElementTable.from_scene(loaded).shape_ids
    for k, shape_id in enumerate(table.shape_ids):
        first = sum(table.element_counts[:k])
        np.testing.assert_allclose(
            np.asarray(table.p_hit)[first : first + table.element_counts[k]],
            fitted[f"fitted/elements.{shape_id}.p_hit"],
            atol=1e-6,
        )


PLANAR_ROOM = """<scene version="3.0.0">
    <sensor type="lidar" id="lidar"><string name="pattern" value="planar-360"/></sensor>
    <shape type="cube" id="walls"><transform name="to_world"><scale x="6" y="4" z="1"/></transform>
        <bsdf type="lidar_material"><integer name="label" value="1"/></bsdf></shape>
    <shape type="cylinder" id="post">
        <point name="p0" x="2" y="1" z="-1"/><point name="p1" x="2" y="1" z="1"/><float name="radius" value="0.3"/>
        <bsdf type="lidar_material"><integer name="label" value="2"/></bsdf></shape>
    <shape type="rectangle" id="glass">
        <transform name="to_world"><scale x="1.5" y="1"/><rotate y="1" angle="90"/><translate x="-3"/></transform>
        <bsdf type="lidar_material"><float name="p_hit" value="{p_glass}"/><integer name="label" value="3"/></bsdf>
    </shape>
</scene>
"""


def write_carmen(path, log) -> None:
    """The scans of a planar log as CARMEN FLASER lines (misses at the no-return value)."""
    lines = []
    for s in range(log.shape[0]):
        ranges = np.where(log.hit[s, :, 0], log.ranges[s, :, 0], NO_RETURN)
        x, y = log.poses[s, :2, 3]
        theta = np.arctan2(log.poses[s, 1, 0], log.poses[s, 0, 0])
        pose = f"{x:.4f} {y:.4f} {theta:.5f}"
        readings = " ".join(f"{r:.3f}" for r in ranges)
        lines.append(f"FLASER {len(ranges)} {readings} {pose} {pose} {100 + s:.3f} host {100 + s:.3f}")
    path.write_text("\n".join(lines) + "\n")


def test_planar_carmen_log_calibrates_with_the_pattern_from_the_log(tmp_path):
    angles = beam_angles(CARMEN_BEAMS)
    carmen = FiringPattern(
        name="carmen",
        elevation=np.zeros((CARMEN_BEAMS, 1)),
        azimuth=angles[:, None],
        time=np.arange(CARMEN_BEAMS)[:, None] / CARMEN_BEAMS / 150,
        period=1 / 150,
    )
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, 0, 3] = np.linspace(-1.0, 1.0, 12)
    poses[:6, :2, :2] = [[0, -1], [1, 0]]  # facing +y (the glass at x = -3 at the left edge of the scan)
    poses[6:, :2, :2] = [[-1, 0], [0, -1]]  # facing -x, the glass ahead
    truth = tmp_path / "truth.xml"
    truth.write_text(PLANAR_ROOM.format(p_glass=0.3))
    start = tmp_path / "room.xml"
    start.write_text(PLANAR_ROOM.format(p_glass=0.8))
    log = mi_lidar.simulate(mi_lidar.load_scene(truth), carmen, poses=poses, seed=3)
    write_carmen(tmp_path / "room.log", log)

    refused, output = calibrate(tmp_path / "room.log", start, "-p", "elements.*.p_hit", "--out", tmp_path / "no")
    assert refused.exit_code == 2 and f"{CARMEN_BEAMS} beams vs 360" in output and "--force" in output
    args = ("-p", "elements.glass.p_hit", "--out", tmp_path / "out", "--steps", 60, "--pattern", "log")
    result, output = calibrate(tmp_path / "room.log", start, *args)
    assert result.exit_code == 0, output
    fitted = np.load(tmp_path / "out" / "parameters.npz")["fitted/elements.glass.p_hit"]
    assert np.abs(fitted - 0.3).max() < 0.1, fitted  # from 0.8, counting start plus Adam, a few hundred rays
    calibrated = mi_lidar.load_scene(tmp_path / "out" / "scene.xml")
    pattern = scene_lidar_sensor(calibrated).pattern
    assert pattern.shape == (CARMEN_BEAMS, 1)
    np.testing.assert_allclose(pattern.azimuth[:, 0], angles, atol=1e-9)
