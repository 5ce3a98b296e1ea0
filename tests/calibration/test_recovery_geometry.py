"""Recovery of parameters that move rays or geometry (the scene is re-traced at every step).

Each test simulates a log with known values, fits from a perturbed start (or from the effect at
identity) and checks the recovered values against stated tolerances. Seeds are fixed. The
extrinsics fit (200 steps) is marked slow.
"""

import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, pattern, sensor_pose


def poses(n: int, radius: float = 0.4) -> np.ndarray:
    """``n`` sensor poses on a circle of ``radius`` m, each turned by its angle on the circle."""
    return np.stack(
        [sensor_pose(radius * np.cos(a), radius * np.sin(a), a) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    )


@pytest.mark.slow
def test_extrinsics_recovered():
    truth = np.array([0.004, -0.003, 0.006, 0.04, -0.03, 0.02])  # rad, rad, rad, m, m, m
    effect = "extrinsics(" + ", ".join(f"{k}={v}" for k, v in zip(("rx", "ry", "rz", "tx", "ty", "tz"), truth)) + ")"
    scene = mi_lidar.load_scene(scene_dict({"terrain": bowl(n=33, half=16.0)}))
    log = mi_lidar.simulate(
        scene, pattern(500), poses=poses(4), seed=11, model=SensorModel(range_sigma=0.01, effects=parse_effects(effect))
    )
    cal = Calibration(
        scene,
        log,
        ["sensor.extrinsics"],
        model=SensorModel(range_sigma=0.01),
        options=FitOptions(
            steps=200, batch_size=1 << 14, eval_every=10, patience=6, seed=2, learning_rates={"sensor.extrinsics": 2e-3}
        ),
    )
    result = cal.fit()
    error = np.abs(result.fitted["sensor.extrinsics"] - truth)
    assert error[:3].max() < 5e-4 and error[3:].max() < 5e-3, f"errors (rad, m): {np.round(error, 5)}"  # 0.03 deg, 5 mm
    assert result.fitted_nll < result.initial_nll


def test_beam_azimuth_offsets_recovered():
    truth = np.radians(np.random.default_rng(3).uniform(-0.4, 0.4, 16))
    scene = mi_lidar.load_scene(scene_dict({"terrain": bowl(n=33, half=16.0)}))
    text = " ".join(f"{v:.8f}" for v in truth)
    log = mi_lidar.simulate(
        scene,
        pattern(500),
        poses=poses(4),
        seed=12,
        model=SensorModel(range_sigma=0.01, effects=parse_effects(f"beam_offsets(azimuth=[{text}])")),
    )
    cal = Calibration(
        scene,
        log,
        ["sensor.azimuth_offset"],
        model=SensorModel(range_sigma=0.01),
        options=FitOptions(
            steps=150,
            batch_size=1 << 14,
            eval_every=10,
            patience=4,
            seed=2,
            learning_rates={"sensor.azimuth_offset": 1e-3},
        ),
    )
    result = cal.fit()
    error_deg = np.degrees(np.abs(result.fitted["sensor.azimuth_offset"] - truth))
    assert error_deg.max() < 0.1 and np.median(error_deg) < 0.02, f"azimuth errors (deg): {np.round(error_deg, 4)}"
    assert result.fitted_nll < result.initial_nll


def test_terrain_heights_recovered():
    truth_sets = bowl(n=9)
    rng = np.random.default_rng(5)
    truth_sets.vertices[:, 2] += rng.uniform(-0.08, 0.08, len(truth_sets.vertices))  # m
    log = mi_lidar.simulate(
        mi_lidar.load_scene(scene_dict({"terrain": truth_sets})),
        pattern(500),
        poses=poses(4),
        seed=13,
        model=SensorModel(range_sigma=0.01),
    )
    start = bowl(n=9)
    scene = mi_lidar.load_scene(scene_dict({"terrain": start}))
    cal = Calibration(
        scene,
        log,
        ["terrain.terrain.heights"],
        model=SensorModel(range_sigma=0.01),
        options=FitOptions(steps=150, batch_size=1 << 14, eval_every=10, patience=4, seed=2),
    )
    result = cal.fit()
    inner = np.hypot(start.vertices[:, 0], start.vertices[:, 1]) < 7.0  # vertices of triangles hit by many beams
    before = np.abs(start.vertices[inner, 2] - truth_sets.vertices[inner, 2])
    after = np.abs(result.fitted["terrain.terrain.heights"][inner] - truth_sets.vertices[inner, 2])
    assert after.max() < 0.02 and np.median(after) < 0.01, f"height errors (m): {np.round(after, 3)}"
    assert np.median(after) < 0.25 * np.median(before)
    assert result.fitted_nll < result.initial_nll
