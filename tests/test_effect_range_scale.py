"""range_scale: every return is multiplied by the scale, noise included; hits are unchanged.

The same seed with and without the scale draws the same noise (counter-based randomness), so
each range is exactly ``scale`` times the unscaled one (within 2e-6 relative, float32).
"""

import numpy as np

import mi_lidar
from mi_lidar.calibration import scene_dict
from mi_lidar.effects import parse_effects
from mi_lidar.sensor_model import SensorModel

from .calibration.scenes import floor_and_wall, pattern


def simulate(effects: str):
    pose = np.eye(4)
    pose[2, 3] = 2.0
    model = SensorModel(range_sigma=0.03, effects=parse_effects(effects))
    log = mi_lidar.simulate(mi_lidar.load_scene(scene_dict(floor_and_wall())), pattern(300), poses=pose, seed=6,
                            model=model)
    return log.ranges[0], log.hit[0]


def test_ranges_scale():
    clean, clean_hit = simulate("")
    for scale in (0.997, 1.004):
        scaled, hit = simulate(f"range_scale(scale={scale})")
        np.testing.assert_array_equal(hit, clean_hit)
        assert hit.sum() > 2000
        np.testing.assert_allclose(scaled[hit], scale * clean[hit], rtol=2e-6)
