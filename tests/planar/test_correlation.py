"""Shared errors of neighbouring beams: the PIT measure, pairs by (scan, beam), and the fitted copula."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_lidar.core.streams import BeamCorrelation, NeighbourStreams, scan_follows
from mi_lidar.planar.correlation import fit_beam_correlation, lag_correlations, pit_scores

SCANS, BEAMS = 200, 180
SCAN, BEAM = np.divmod(np.arange(SCANS * BEAMS), BEAMS)


def _toy_sample(correlation: BeamCorrelation, seed: int):
    """A wall at 10 m seen with 5 cm noise and 3 % no-returns, neighbouring beams sharing ``correlation``."""
    streams = NeighbourStreams(seed=seed, follows=scan_follows(SCAN, BEAM), correlation=correlation)
    ids = dr.arange(mi.UInt32, SCAN.size)
    u_range = np.asarray(streams.uniform(ids, 0, 1), np.float64)
    u_miss = np.asarray(streams.uniform(ids, 0, 0), np.float64)
    from scipy.special import ndtri

    return 10.0 + 0.05 * ndtri(u_range), u_miss >= 0.03


def test_pit_scores_of_an_exchangeable_measurement_are_standard_normal():
    z, hit = _toy_sample(BeamCorrelation(), 99)
    draws = [_toy_sample(BeamCorrelation(), s) for s in range(16)]
    scores = pit_scores(
        z, hit, np.stack([d[0] for d in draws]), np.stack([d[1] for d in draws]), np.random.default_rng(0)
    )
    # 36,000 independent scores: mean SE 0.005, std SE 0.004 (randomized ties keep the PIT uniform)
    assert np.mean(scores) == pytest.approx(0.0, abs=0.03)
    assert np.std(scores) == pytest.approx(1.0, abs=0.03)


def test_lag_correlations_pair_beams_by_scan_and_beam_in_any_order():
    rng = np.random.default_rng(1)
    latent = rng.standard_normal(SCAN.size)
    scores = latent + np.roll(latent, 1) * (BEAM > 0)  # lag-one correlation 0.5 (sum of neighbours)
    order = rng.permutation(SCAN.size)
    lags = lag_correlations(scores[order], SCAN[order], BEAM[order], (1, 2))
    assert lags[0] == pytest.approx(0.5, abs=0.03)
    assert lags[1] == pytest.approx(0.0, abs=0.03)


def test_the_fit_finds_the_shared_errors_of_the_measured_scans():
    true = BeamCorrelation(shared=0.9, rho=0.95)
    z, hit = _toy_sample(true, 1234)
    chosen, summary = fit_beam_correlation(_toy_sample, z, hit, SCAN, BEAM)
    assert np.allclose(summary["sampled"], summary["real"], atol=0.05)
    assert chosen.lag(1) == pytest.approx(true.lag(1), abs=0.1)
    assert np.all(np.abs(summary["uncorrelated"]) < 0.05)


def test_the_fit_adds_no_correlation_to_independent_beams():
    z, hit = _toy_sample(BeamCorrelation(), 1234)
    chosen, summary = fit_beam_correlation(_toy_sample, z, hit, SCAN, BEAM)
    assert chosen.lag(1) < 0.1
    assert np.all(np.abs(summary["real"]) < 0.05)
