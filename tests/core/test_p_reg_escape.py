"""P-Reg's law for a beam that met nothing: a Gaussian of the escaped returns, or uniform, by held-out likelihood.

Before, an escaped beam's return was always uniform on ``[0, z_max]``. In a crude 3D scene (the Ouster
frame's ``fit-scene`` hybrid scene) most escaped beams return at a few to 30 m, from objects the scene
lacks, so P-Reg's sampled scans put those returns anywhere to 120 m (p90 |range error| 67 m). The
fit now also offers ``N(escape_mean, escape_sigma^2)`` of the escaped training returns and keeps the
law that scores better on held-out beams. Synthetic beams, fixed seeds; tolerances with each assertion.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.densities.preg import PRegDensity, fit_p_reg
from mi_lidar.planar.beams import base_model

from .escaped_beams import escaped_beams

Z_MAX = 80.0  # m
ESCAPE_NULL = 0.3  # share of escaped beams that report nothing


def beams(n: int, seed: int, escaped_returns):
    return escaped_beams(n, seed, ESCAPE_NULL, escaped_returns)


def fit(escaped_returns) -> tuple[PRegDensity, list, object]:
    """P-Reg fitted on 2 x 3,000 beams (seed 0), scored on 2 x 3,000 others (seed 1); also the held-out beams."""
    train, _ = beams(3000, 0, escaped_returns)
    _, check = beams(3000, 1, escaped_returns)

    def held_out(density) -> float:
        return float(-np.mean(check.log_likelihood(base_model(density))))

    density, table = fit_p_reg(train, held_out, h_ranges=(1.0,), h_incidences=(20.0,), z_max=Z_MAX)
    return density, table, check


def near(rng, n):
    return rng.normal(12.0, 3.0, n)  # objects the scene lacks, 12 m +- 3 m away


def spread(rng, n):
    return rng.uniform(0.0, Z_MAX, n)  # spurious readings anywhere in the sensor's span


def test_escaped_returns_near_the_sensor_get_a_gaussian_that_samples_them_where_they_were():
    """Chosen: the Gaussian, held out better than the uniform by > 1 nat per escaped return (expected
    log(80) - 0.5 log(2 pi e 3.3^2) = 1.6, the fitted spread being shrunk towards the uniform's); its mean
    within 0.6 m of 12 m (30 pseudo-returns at 40 m pull it by 0.4 m); the sampled escaped returns'
    median within 0.5 m of the fitted mean, and 90 % of them within 10 m of 12 m (uniform: within 10 m
    for 25 %)."""
    density, table, check = fit(near)
    assert density.choices["escape"] == "gaussian", table
    nll = {row[2]: row[-1] for row in table}
    escaped_share = 0.5 * (1 - ESCAPE_NULL)
    assert nll["uniform"] - nll["gaussian"] > 1.0 * escaped_share, nll
    assert abs(float(density["escape_mean"][0]) - 12.0) < 0.6, density["escape_mean"]
    z, hit = check.sample(base_model(density), 0)
    escaped = np.arange(z.size) >= z.size // 2
    drawn = z[escaped & hit]
    assert abs(np.median(drawn) - float(density["escape_mean"][0])) < 0.5, np.median(drawn)
    assert np.mean(np.abs(drawn - 12.0) < 10.0) > 0.9, np.mean(np.abs(drawn - 12.0) < 10.0)


def test_escaped_returns_spread_over_the_span_keep_the_uniform_law():
    """Returns uniform on [0, z_max]: the uniform scores better held out (the Gaussian of the same moments
    loses 0.18 nats per escaped return and its tails beyond the span), so it is kept."""
    density, table, _ = fit(spread)
    assert density.choices["escape"] == "uniform", table
    nll = {row[2]: row[-1] for row in table}
    assert nll["gaussian"] > nll["uniform"], nll


def test_a_density_built_without_the_choice_keeps_the_uniform_escape():
    """What a P-Reg file written before the choice holds: no ``escape`` option, the uniform law."""
    assert PRegDensity(z_max=Z_MAX).choices["escape"] == "uniform"
