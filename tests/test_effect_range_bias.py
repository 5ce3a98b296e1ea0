"""range_bias: every return of a beam moves by that beam's bias; hits and noise draws are unchanged.

The same seed with and without the bias draws the same noise (counter-based randomness), so the
ranges differ by exactly ``bias[beam]`` (within 2e-5 m, float32 at 40 m).
"""

import numpy as np

import mi_lidar
from mi_lidar.calibration import scene_dict
from mi_lidar.effects import parse_effects
from mi_lidar.sensor_model import SensorModel

from .calibration.scenes import floor_and_wall, pattern

BIAS = np.round(np.linspace(-0.05, 0.05, 16), 4)  # m


def simulate(effects: str):
    pose = np.eye(4)
    pose[2, 3] = 2.0
    model = SensorModel(range_sigma=0.03, effects=parse_effects(effects))
    log = mi_lidar.simulate(mi_lidar.load_scene(scene_dict(floor_and_wall())), pattern(300), poses=pose, seed=5,
                            model=model)
    return log.ranges[0], log.hit[0]


def test_each_beam_shifts_by_its_bias():
    clean, clean_hit = simulate("")
    biased, hit = simulate(f"range_bias(bias=[{' '.join(f'{b:.4f}' for b in BIAS)}])")
    np.testing.assert_array_equal(hit, clean_hit)
    shift = np.where(hit, biased - clean, np.nan)
    for beam in range(16):
        row = shift[beam][hit[beam]]
        assert row.size > 50
        np.testing.assert_allclose(row, BIAS[beam], atol=2e-5)


def test_single_value_applies_to_every_beam():
    clean, hit = simulate("")
    biased, _ = simulate("range_bias(bias=0.02)")
    np.testing.assert_allclose((biased - clean)[hit], 0.02, atol=2e-5)
