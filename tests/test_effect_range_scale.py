"""range_scale: every return is multiplied by the scale, noise included; hits are unchanged.

The same seed with and without the scale draws the same noise (counter-based randomness), so
each range is exactly ``scale`` times the unscaled one (within 2e-6 relative, float32).
"""

import numpy as np

from .calibration.scenes import floor_and_wall_scan


def simulate(effects: str):
    return floor_and_wall_scan(effects, seed=6)


def test_ranges_scale():
    clean, clean_hit = simulate("")
    for scale in (0.997, 1.004):
        scaled, hit = simulate(f"range_scale(scale={scale})")
        np.testing.assert_array_equal(hit, clean_hit)
        assert hit.sum() > 2000
        np.testing.assert_allclose(scaled[hit], scale * clean[hit], rtol=2e-6)
