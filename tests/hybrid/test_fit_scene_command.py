"""fit-scene says what it wrote, and warns that a planar log cannot show a hybrid scene's ground and vegetation."""

import numpy as np

import mi_lidar
from mi_lidar.hybrid.commands import fit_scene

from ..conftest import SCENES


def test_a_planar_log_is_warned_about(tmp_path, capsys):
    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3], poses[:, 2, 3] = [0.0, 0.5, 1.0], 0.5
    log = mi_lidar.simulate(scene, poses=poses, seed=1)
    log.attributes["label"] = np.ones_like(log.hit, np.int32)  # the fit reads labels
    path = log.save(tmp_path / "room.npz")
    xml = fit_scene(path, tmp_path / "fitted", preview=False)
    said = capsys.readouterr().err
    assert xml.is_file() and f"warning: {path} is a planar log (every beam in one plane)" in said  # one line
