"""Intensity on the real Ouster OS-1-32 frame: the fitted model beats a constant per beam on held-out columns."""

import pytest

from mi_lidar.io import read_any
from mi_lidar.loop.real_intensity import intensity_experiment, intensity_figure


@pytest.mark.slow
def test_fitted_reflectivity_beats_constant_per_beam(shared_data, tmp_path):
    """REFLECTIVITY of the odd columns: the fitted model correlates better than the per-beam constant
    (measured at 150 steps: r 0.59 vs 0.31). Its intensity NLL does not beat the baseline yet (6.85 vs
    4.18 nats/return): a known gap, not asserted. About 40 s."""
    log = read_any(shared_data / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap")
    scores = intensity_experiment(log, "reflectivity", "reflectivity", steps=100)
    assert scores.correlation > scores.baseline_correlation + 0.2, scores.summary()
    assert intensity_figure([scores], tmp_path / "f.png").stat().st_size > 10_000
