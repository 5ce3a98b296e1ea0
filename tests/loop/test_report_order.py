"""Breakdown groups sort numerically, and relative gains are reported only where meaningful."""

import math

import numpy as np

from mi_lidar.loop.compare import RayTable, breakdown
from mi_lidar.loop.selection import relative_gain


def table(azimuth: np.ndarray) -> RayTable:
    n = azimuth.size
    zeros, ones = np.zeros(n), np.ones(n, bool)
    return RayTable(
        ll=-np.arange(n, dtype=float),
        measured=zeros + 5,
        hit=ones,
        sim_range=zeros + 5,
        sim_hit=ones,
        nominal=zeros + 5,
        cos_incidence=zeros + 1,
        kind=np.zeros(n, int),
        label=np.zeros(n, int),
        shape=np.zeros(n, int),
        beam=np.arange(n) % 12,
        column=np.arange(n),
        scan=np.zeros(n, int),
        azimuth=azimuth,
    )


def test_azimuth_and_beam_groups_sort_numerically():
    t = table(np.linspace(-179, 179, 24))
    groups = [r["group"] for r in breakdown(t, "azimuth")]
    starts = [int(g.split("..")[0]) for g in groups]
    assert starts == sorted(starts) and starts[0] == -180 and len(groups) == 12
    beams = [r["group"] for r in breakdown(t, "beam")]
    assert beams == [f"beam {b:03d}" for b in range(12)]


def test_relative_gain_only_away_from_zero_nll():
    assert relative_gain(0.5, -2.0) == 25.0
    assert math.isnan(relative_gain(0.5, 0.3))
