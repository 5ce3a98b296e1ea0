"""compare warns when its sampled scan is the log itself: a log simulated by the same model with the same seed."""

import numpy as np

import mi_lidar
from mi_lidar.loop.compare import compare

from ..conftest import SCENES


def test_the_same_model_and_seed_are_warned_about_and_another_seed_is_not():
    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[:, 0, 3] = [0.0, 0.5]
    log = mi_lidar.simulate(scene, poses=poses, seed=0)
    same = compare(log, scene, seed=0)
    assert same.headline["range_error_median"] == 0.0  # the README's loop showed this as a result
    (warning,) = same.warnings
    assert "equals the log ray for ray" in warning and "seed 0 (the log records seed 0)" in warning
    other = compare(log, scene, seed=1)
    assert other.warnings == [] and other.headline["range_error_median"] > 0.0
