"""beam_offsets: each beam turns by its elevation and azimuth offsets, and hits land where geometry says.

A sensor 2 m above an opaque floor faces a wall 10 m ahead; without noise every simulated range
must equal the analytic range of the beam turned by its offsets (within 1e-4 relative, float32
tracing), and differ from the unturned beam's range.
"""

import numpy as np

from mi_lidar.core.effects import BeamOffsets

from .calibration.scenes import SCAN_HEIGHT, analytic_ranges, floor_and_wall_scan, pattern, unit_directions


def simulate(effects: str):
    """The pattern, (16, 360) ranges (m) and hit flags of a noiseless scan with the effects ``effects``."""
    return pattern(360), *floor_and_wall_scan(effects, seed=0, range_sigma=0.0, firings=360)


def test_offsets_move_hits_where_geometry_says():
    elevation = np.radians(np.linspace(-0.5, 0.5, 16))
    azimuth = np.radians(np.linspace(1.0, -1.0, 16))
    text = lambda a: " ".join(f"{x:.8f}" for x in a)  # noqa: E731
    p, ranges, hit = simulate(f"beam_offsets(elevation=[{text(elevation)}], azimuth=[{text(azimuth)}])")
    turned = unit_directions(p.elevation + elevation[:, None], p.azimuth + azimuth[:, None])
    expected = analytic_ranges(np.array([0, 0, SCAN_HEIGHT]), turned)
    nominal = analytic_ranges(np.array([0, 0, SCAN_HEIGHT]), unit_directions(p.elevation, p.azimuth))
    finite = np.isfinite(expected) & (expected < 100)
    assert finite.sum() > 2000 and np.array_equal(hit[finite], np.ones(finite.sum(), bool))
    np.testing.assert_allclose(ranges[finite], expected[finite], rtol=1e-4)
    assert np.median(np.abs(ranges[finite] - nominal[finite])) > 1e-3  # the offsets did move the hits


def test_last_value_repeats_for_remaining_beams():
    _, one, _ = simulate("beam_offsets(elevation=[0.004])")
    _, full, _ = simulate(f"beam_offsets(elevation=[{' '.join(['0.004'] * 16)}])")
    np.testing.assert_array_equal(one, full)


def test_default_is_identity():
    assert np.allclose(np.asarray(BeamOffsets()["elevation"]), 0.0)
    _, default, _ = simulate("beam_offsets")
    _, none, _ = simulate("")
    np.testing.assert_allclose(default, none, rtol=1e-6, equal_nan=True)  # float32 rotation round-off
