"""The last steps of mi-lidar's planar fit: its tables' far tails and no-returns set against the training log.

Hard EM (:func:`~mi_lidar.planar.models.fit_permeable_map`) gives each return to one segment, so the
tables also learn far returns that the pass-through already explains. These steps correct that on
training beams only: the tails scaled by likelihood (:func:`fit_tails`), the short tail set so that
sampled scans hold as many short returns as the measured ones (:func:`match_short_returns`), and the
no-return probabilities matched to the training beams (:func:`match_misses`). The last two trade a
little training likelihood (at most :data:`MISS_TOLERANCE`) for scans that look like the sensor's.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.densities import NPRegDensity
from mi_lidar.planar.beams import AngularMixture, base_model, golden_section
from mi_lidar.planar.raymarch import PlanarTrace


def training_nll(beams: AngularMixture, density: NPRegDensity, z_max: float) -> float:
    """Mean score (nats per beam) of ``beams`` under the planar sensor model around ``density``."""
    return float(-np.mean(beams.log_likelihood(base_model(density))))


FAR = 0.5  # m: a return farther than this from its segment's surface is in the table's short or long tail


def with_tails(density: NPRegDensity, short: float, long: float) -> NPRegDensity:
    """``density`` with every state's mass more than :data:`FAR` short of the surface scaled by ``short``
    and more than :data:`FAR` long by ``long`` (then each state renormalised; P(no return) unchanged)."""
    centres = 0.5 * (density.edges[1:] + density.edges[:-1])
    scale = np.where(centres < -FAR, short, np.where(centres > FAR, long, 1.0))
    return density.with_tables(mass=density.mass * scale)


def fit_tails(beams: AngularMixture, density: NPRegDensity, z_max: float, iterations: int = 10) -> NPRegDensity:
    """The tables of ``density`` with their short and long tails scaled by maximum likelihood on ``beams``.

    Hard EM gives each return to one segment, so a table also learns far returns that the pass-through
    already explains (a return behind a wall is counted in the wall's table and in its permeability):
    the model then draws more short and long returns than the log holds, on its training beams too. The
    two factors (in [0.02, 2], 1: unchanged) are found one after the other by golden-section search on
    the mean score of ``beams`` (:func:`~mi_lidar.planar.beams.golden_section`, ``iterations`` steps
    each), with the beams' angular spread: much of the short tail of a beam's own trace is its
    neighbours' nearer returns, which the spread explains. The spread is fitted again after. On Intel
    (2026-11-26): short 0.75, long 0.28; test NLL 3.260 -> 3.252; of the sampled test returns, short
    ones (> 0.5 m) 5.6 -> 4.3-5.0 % and long ones 5.7 -> 4.9-5.1 % (measured 3.6 and 4.1 %).
    """

    def nll(short: float, long: float) -> float:
        return training_nll(beams, with_tails(density, short, long), z_max)

    short = golden_section(lambda x: nll(x, 1.0), 0.02, 2.0, iterations)
    long = golden_section(lambda x: nll(short, x), 0.02, 2.0, iterations)
    if nll(short, long) >= nll(1.0, 1.0):
        return density
    return with_tails(density, short, long)


MISS_TOLERANCE = 0.002  # nats per beam: the training score :func:`match_misses` may lose


def match_misses(beams: AngularMixture, density: NPRegDensity, z_max: float) -> NPRegDensity:
    """``density`` with every state's P(no return) scaled so that ``beams`` miss as often as the model predicts.

    The tables' no-return probabilities come from the no-returns counted at each beam's first occupied
    cell, smoothed across states, and the model predicted more no-returns than its training beams have
    (Intel: 3.05 % against 2.57 %), so its sampled scans missed too often. The likelihood is nearly flat
    in a common factor on them (Intel: within 1e-4 nats per beam from 0.8 to 1), so the factor is set by
    the training beams' no-return rate instead: P(miss) is linear in it, ``P(miss) = P0 + factor (P1 -
    P0)`` with ``P0`` (no table misses, only escapes) and ``P1`` (the tables as they are) the mean
    P(miss) of ``beams``; each probability is capped at 1. The escape state (a beam that met no cell) is
    left as it is: its P(null) is counted from its own beams, not smoothed across states (scaled with
    the rest, Edmonton's beams that met no cell were predicted to miss 34 % of the time where 41 % did;
    left, 40 %, test NLL 4.1754 -> 4.1743). Kept only if the mean training score loses less than
    :data:`MISS_TOLERANCE`; otherwise ``density`` is returned unchanged.
    """

    def with_factor(factor: float) -> NPRegDensity:
        scaled = np.minimum(density.p_null * factor, 1.0)
        escape = density.grid.size  # the escape state's index (NPRegDensity.state)
        scaled[escape:] = density.p_null[escape:]
        return density.with_tables(p_null=scaled)

    def p_miss(d: NPRegDensity) -> float:
        return float(np.mean(beams.p_miss(base_model(d))))

    p0, p1 = p_miss(with_factor(0.0)), p_miss(density)
    if p1 - p0 < 1e-9:
        return density
    matched = with_factor(max(0.0, (float(np.mean(~beams.hit)) - p0) / (p1 - p0)))
    kept = training_nll(beams, matched, z_max) < training_nll(beams, density, z_max) + MISS_TOLERANCE
    return matched if kept else density


SHORT_DRAWS = 4  # sampled scans (seeds 0, 1, ...) that count a model's short returns
SHORT_STEPS = 8  # bisection steps of :func:`match_short_returns`


def short_share(z: np.ndarray, hit: np.ndarray, nominal: np.ndarray) -> float:
    """Share of beams that returned more than :data:`FAR` short of their nominal range."""
    return float(np.mean(hit & np.isfinite(nominal) & (z < nominal - FAR)))


def match_short_returns(beams: AngularMixture, trace: PlanarTrace, density: NPRegDensity, z_max: float) -> NPRegDensity:
    """``density`` with its short tail scaled down until scans sampled at ``beams`` hold as many short returns
    (more than :data:`FAR` short of the nominal range) as the measured ones of ``trace`` (the same beams).

    The likelihood trades a too heavy short tail for little: after :func:`fit_tails` the Intel model
    drew 4.7 % short returns on its training beams where the sensor gave 4.0 %, and scaling the tail to
    match them cost 0.001 nats per training beam while the one-draw p90 |error| fell 0.906 -> 0.862 m.
    The factor (in [0.02, 1]: never heavier) is found by bisection on the share in
    :data:`SHORT_DRAWS` scans sampled with fixed seeds, and kept only if the mean training score loses
    less than :data:`MISS_TOLERANCE`; otherwise ``density`` is returned unchanged.
    """
    measured = short_share(trace.z, trace.hit, trace.nominal)

    def sampled(factor: float) -> float:
        model = base_model(with_tails(density, factor, 1.0))
        return float(np.mean([short_share(*beams.sample(model, seed), trace.nominal) for seed in range(SHORT_DRAWS)]))

    if sampled(1.0) <= measured:
        return density
    low, high = 0.02, 1.0
    for _ in range(SHORT_STEPS):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if sampled(middle) < measured else (low, middle)
    matched = with_tails(density, 0.5 * (low + high), 1.0)
    kept = training_nll(beams, matched, z_max) < training_nll(beams, density, z_max) + MISS_TOLERANCE
    return matched if kept else density
