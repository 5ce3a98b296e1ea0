"""Weighted state samples: a sample of weight w counts as w samples in NP-Reg's and P-Reg's fits.

A soft E step gives a ray one sample per element that may have produced its outcome, weighted by the
element's posterior share (:class:`~mi_lidar.core.densities.samples.StateSamples`; fit-sensor still credits
each ray wholly to its most likely element: the soft step scored worse held out). Synthetic states (fixed
seed): nominal ranges 1-20 m, some unknown incidences and escaped rays, two labels, three beams, 10 % misses
and 10 % returns short of or behind the element; the fits keep labels and beams apart.
"""

import dataclasses

import numpy as np
import pytest

from mi_lidar.core.densities.histogram import fit_np_reg
from mi_lidar.core.densities.preg import fit_p_reg
from mi_lidar.core.densities.samples import StateSamples
from mi_lidar.core.densities.tables import StateGrid


def states(n: int = 20_000) -> StateSamples:
    rng = np.random.default_rng(3)
    r = rng.uniform(1.0, 20.0, n)
    r[: n // 10] = np.nan  # escaped rays
    incidence = np.where(np.arange(n) < n // 5, np.nan, rng.uniform(0.0, 60.0, n))
    hit = rng.random(n) > 0.1
    stray = (rng.random(n) < 0.1) * rng.uniform(-1.0, 3.0, n)
    z = np.where(np.isnan(r), rng.uniform(0.0, 30.0, n), r + 0.02 * rng.standard_normal(n) + stray)
    return StateSamples(r, incidence, rng.integers(0, 3, n), rng.integers(0, 2, n), np.where(hit, z, np.nan), hit)


def fits(samples: StateSamples) -> dict[str, np.ndarray]:
    """The tables of NP-Reg and P-Reg fitted to ``samples`` (one candidate setting each)."""
    grid = StateGrid(range_edges=list(np.arange(0.0, 21.0)), incidence_edges=[0, 20, 40, 60, 90], n_labels=2, n_beams=3)
    np_reg, _ = fit_np_reg(samples, grid, lambda d: 0.0, h_ranges=(1.0,), h_incidences=(10.0,))
    p_reg, _ = fit_p_reg(samples, lambda d: 0.0, h_ranges=(1.0,), h_incidences=(20.0,), n_labels=2, n_beams=3)
    escape = {name: p_reg.settings()[name] for name in ("escape_null", "escape_mean", "escape_sigma")}
    return {
        **{f"np_reg {k}": v for k, v in np_reg.tables().items()},
        **{f"p_reg {k}": np.asarray(v) for k, v in p_reg.tables().items()},
        **{f"p_reg {k}": np.asarray(v, np.float64) for k, v in escape.items()},
    }


def test_weights_of_one_are_the_unweighted_fit():
    """Weights all 1, given or by default, fit the same tables bit for bit (and the same as before weights
    existed: checked against the parent commit's fits of these samples)."""
    samples = states()
    ones = dataclasses.replace(samples, weight=np.ones(samples.n))
    assert np.array_equal(samples.weight, np.ones(samples.n))
    default, given = fits(samples), fits(ones)
    for name, table in default.items():
        assert np.array_equal(table, given[name], equal_nan=True), name


def test_a_sample_of_weight_two_counts_as_two_samples():
    """Every fourth sample weighted 2 fits what that sample given twice fits (NP-Reg's counts exactly, P-Reg's
    regressions to 1e-9: only the order of the sums differs); half weights fit other tables (the weights count)."""
    samples = states()
    twice = np.arange(samples.n) % 4 == 0
    weighted = dataclasses.replace(samples, weight=np.where(twice, 2.0, 1.0))
    repeated = samples.take(np.concatenate([np.arange(samples.n), np.flatnonzero(twice)]))
    by_weight, by_copy = fits(weighted), fits(repeated)
    halved = fits(dataclasses.replace(samples, weight=np.where(twice, 0.5, 1.0)))
    for name, table in by_weight.items():
        if name.startswith("np_reg"):
            assert np.allclose(table, by_copy[name], rtol=1e-12, atol=0, equal_nan=True), name
        else:
            assert np.allclose(table, by_copy[name], rtol=1e-9, atol=1e-12, equal_nan=True), name
    for name in ("np_reg mass", "np_reg p_null", "p_reg p_null", "p_reg mu", "p_reg sigma", "p_reg escape_mean"):
        assert not np.allclose(halved[name], by_weight[name], rtol=1e-6, atol=0), name


def test_a_weight_per_sample_is_checked_and_kept_by_take():
    """``take`` keeps each sample's weight; a weight array of another length is refused, naming the shapes."""
    from mi_lidar.core.errors import ParameterError

    samples = dataclasses.replace(states(10), weight=np.arange(10.0))
    assert np.array_equal(samples.take(np.array([7, 2])).weight, [7.0, 2.0])
    with pytest.raises(ParameterError, match="arrays of different shapes"):
        dataclasses.replace(samples, weight=np.ones(9))
