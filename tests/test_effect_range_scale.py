"""range_scale: every return's location is multiplied by the scale, its noise is not; hits are unchanged.

The same seed with and without the scale draws the same noise (counter-based randomness), so each
range moves by exactly ``(scale - 1)`` times its noiseless range (``z = scale * r + noise``), and the
scale commutes with the noise laws.
"""

import numpy as np

from .calibration.scenes import floor_and_wall_scan

SIGMA = 0.03  # m, the elements' own noise


def simulate(effects: str, range_sigma: float = SIGMA):
    return floor_and_wall_scan(effects, seed=6, range_sigma=range_sigma)


def test_the_scale_moves_the_location_not_the_noise():
    """Tolerance 2e-5 m: float32 at 10 m; scaling the noise too would move ranges by up to 4e-4 m more."""
    clean, clean_hit = simulate("")
    noiseless, _ = simulate("", range_sigma=1e-7)
    for scale in (0.997, 1.004):
        scaled, hit = simulate(f"range_scale(scale={scale})")
        np.testing.assert_array_equal(hit, clean_hit)
        assert hit.sum() > 2000
        np.testing.assert_allclose(scaled[hit] - clean[hit], (scale - 1.0) * noiseless[hit], rtol=0, atol=2e-5)


def test_the_scale_and_a_noise_law_commute():
    noise, scale = "range_noise(law=proportional, k=0.01)", "range_scale(scale=1.004)"
    first, hit = simulate(f"{noise}, {scale}")
    second, hit_second = simulate(f"{scale}, {noise}")
    np.testing.assert_array_equal(hit, hit_second)
    np.testing.assert_allclose(first[hit], second[hit], rtol=1e-6)


def test_the_scale_and_a_per_beam_bias_commute_on_surfaces():
    """``z = scale * r + bias`` whichever comes first in the model; before, a bias placed before the scale was
    scaled too, ``scale * (r + bias)``: 2e-4 m apart here, beyond the float32 tolerance of 2e-5 m at 10 m."""
    bias, scale = "range_bias(bias=0.05)", "range_scale(scale=1.004)"
    first, hit = simulate(f"{bias}, {scale}")
    second, hit_second = simulate(f"{scale}, {bias}")
    clean, _ = simulate("")
    noiseless, _ = simulate("", range_sigma=1e-7)
    np.testing.assert_array_equal(hit, hit_second)
    np.testing.assert_allclose(first[hit], second[hit], rtol=0, atol=2e-5)
    np.testing.assert_allclose(first[hit] - clean[hit], 0.004 * noiseless[hit] + 0.05, rtol=0, atol=2e-5)
