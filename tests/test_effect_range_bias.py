"""range_bias: every return of a beam moves by that beam's bias; hits and noise draws are unchanged.

The same seed with and without the bias draws the same noise (counter-based randomness), so the
ranges differ by exactly ``bias[beam]`` (within 2e-5 m, float32 at 40 m).
"""

import numpy as np

from .calibration.scenes import floor_and_wall_scan

BIAS = np.round(np.linspace(-0.05, 0.05, 16), 4)  # m


def simulate(effects: str):
    return floor_and_wall_scan(effects, seed=5)


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
