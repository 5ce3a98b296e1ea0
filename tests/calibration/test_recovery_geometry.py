"""Recovery of parameters that move rays or geometry (the scene is re-traced at every step).

Each test simulates a log with known values (the beam offsets of both axes, the extrinsics, the terrain
heights), fits from a perturbed start (or from the effect at identity) and checks the recovered values
against stated tolerances. Seeds are fixed. The extrinsics fit (200 steps) is marked slow.
"""

import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, circle_poses, pattern


@pytest.mark.slow
def test_extrinsics_recovered():
    truth = np.array([0.004, -0.003, 0.006, 0.04, -0.03, 0.02])  # rad, rad, rad, m, m, m
    effect = "extrinsics(" + ", ".join(f"{k}={v}" for k, v in zip(("rx", "ry", "rz", "tx", "ty", "tz"), truth)) + ")"
    scene = mi_lidar.load_scene(scene_dict({"terrain": bowl(n=33, half=16.0)}))
    log = mi_lidar.simulate(
        scene,
        pattern(500),
        poses=circle_poses(4),
        seed=11,
        model=SensorModel(range_sigma=0.01, effects=parse_effects(effect)),
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


@pytest.mark.parametrize(
    "axis,spread_deg,seeds,rate,max_deg,median_deg",
    [("elevation", 0.3, (2, 7), 5e-4, 0.05, 0.05), ("azimuth", 0.4, (3, 12), 1e-3, 0.1, 0.02)],
    ids=("elevation", "azimuth"),
)
def test_beam_offsets_recovered(axis, spread_deg, seeds, rate, max_deg, median_deg):
    """Per-beam offsets drawn in +-``spread_deg`` (seeded by ``seeds[0]``, log seed ``seeds[1]``) are fitted
    back from zero at learning rate ``rate`` to ``max_deg`` at most and ``median_deg`` in the median (deg)."""
    truth = np.radians(np.random.default_rng(seeds[0]).uniform(-spread_deg, spread_deg, 16))
    scene = mi_lidar.load_scene(scene_dict({"terrain": bowl(n=33, half=16.0)}))
    text = " ".join(f"{v:.8f}" for v in truth)
    log = mi_lidar.simulate(
        scene,
        pattern(500),
        poses=circle_poses(4),
        seed=seeds[1],
        model=SensorModel(range_sigma=0.01, effects=parse_effects(f"beam_offsets({axis}=[{text}])")),
    )
    name = f"sensor.{axis}_offset"
    cal = Calibration(
        scene,
        log,
        [name],
        model=SensorModel(range_sigma=0.01),
        options=FitOptions(
            steps=150, batch_size=1 << 14, eval_every=10, patience=4, seed=2, learning_rates={name: rate}
        ),
    )
    result = cal.fit()
    error_deg = np.degrees(np.abs(result.fitted[name] - truth))
    assert error_deg.max() < max_deg and np.median(error_deg) < median_deg, (
        f"{axis} errors (deg): {np.round(error_deg, 4)}"
    )
    assert result.fitted_nll < result.initial_nll


def test_terrain_heights_recovered():
    truth_sets = bowl(n=9)
    rng = np.random.default_rng(5)
    truth_sets.vertices[:, 2] += rng.uniform(-0.08, 0.08, len(truth_sets.vertices))  # m
    log = mi_lidar.simulate(
        mi_lidar.load_scene(scene_dict({"terrain": truth_sets})),
        pattern(500),
        poses=circle_poses(4),
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
