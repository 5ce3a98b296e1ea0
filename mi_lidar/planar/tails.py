"""The last steps of mi-lidar's planar fit: its tables' far tails and no-returns set against the training log.

The EM (:func:`~mi_lidar.planar.permeable.fit_permeable_map`) shares a return behind a wall between the
wall's table and what lies behind it, so the tables also learn part of the far returns that the
pass-through already explains. These steps correct that on
training beams only: the tails scaled by likelihood (:func:`fit_tails`), the short tail set so that
sampled scans hold as many short returns as the measured ones (:func:`match_short_returns`), and the
no-return probabilities matched to the training beams (:func:`match_misses`). The last two trade a
little training likelihood (at most :data:`MISS_TOLERANCE`) for scans that look like the sensor's.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.densities import NPRegDensity
from mi_lidar.planar.angular import AngularMixture
from mi_lidar.planar.beams import base_model, golden_section
from mi_lidar.planar.trace import PlanarTrace


def training_nll(beams: AngularMixture, density: NPRegDensity) -> float:
    """Mean score (nats per beam) of ``beams`` under the planar sensor model around ``density``."""
    return float(-np.mean(beams.log_likelihood(base_model(density))))


FAR = 0.5  # m: a return farther than this from its segment's surface is in the table's short or long tail


def with_tails(density: NPRegDensity, short: float, long: float) -> NPRegDensity:
    """``density`` with every state's mass more than :data:`FAR` short of the surface scaled by ``short``
    and more than :data:`FAR` long by ``long`` (then each state renormalised; P(no return) unchanged)."""
    centres = 0.5 * (density.edges[1:] + density.edges[:-1])
    scale = np.where(centres < -FAR, short, np.where(centres > FAR, long, 1.0))
    return density.with_tables(mass=density.mass * scale)


def fit_tails(beams: AngularMixture, density: NPRegDensity, iterations: int = 10) -> NPRegDensity:
    """The tables of ``density`` with their short and long tails scaled by maximum likelihood on ``beams``.

    The EM shares a return behind a wall between the wall's table and the cells behind it, so a table
    also learns part of the far returns that the pass-through already explains: the model then draws
    more short and long returns than the log holds, on its training beams too. The
    two factors (in [0.02, 2], 1: unchanged) are found one after the other by golden-section search on
    the mean score of ``beams`` (:func:`~mi_lidar.planar.beams.golden_section`, ``iterations`` steps
    each), with the beams' angular spread: much of the short tail of a beam's own trace is its
    neighbours' nearer returns, which the spread explains. The spread is fitted again after. On Intel
    (2026-11-26, with the hard EM of that day): short 0.75, long 0.28; test NLL 3.260 -> 3.252; of the
    sampled test returns, short ones (> 0.5 m) 5.6 -> 4.3-5.0 % and long ones 5.7 -> 4.9-5.1 % (measured
    3.6 and 4.1 %).
    """

    def nll(short: float, long: float) -> float:
        return training_nll(beams, with_tails(density, short, long))

    short = golden_section(lambda x: nll(x, 1.0), 0.02, 2.0, iterations)
    long = golden_section(lambda x: nll(short, x), 0.02, 2.0, iterations)
    if nll(short, long) >= nll(1.0, 1.0):
        return density
    return with_tails(density, short, long)


MISS_TOLERANCE = 0.002  # nats per beam: the training score :func:`match_misses` may lose
MISS_BAND_BEAMS = 1000  # training beams (by their first occupied cell) each range band of :func:`match_misses` holds
MISS_ROUNDS = 3  # rounds of :func:`match_misses`' per-band update


def miss_bands(first_range: np.ndarray, edges) -> np.ndarray:
    """Range band edges (m) for :func:`match_misses`: ``edges`` with neighbouring bins merged, from the far
    end, until each band holds at least :data:`MISS_BAND_BEAMS` of the finite ``first_range`` (or one band)."""
    ranges = first_range[np.isfinite(first_range)]
    bands = [float(e) for e in edges]
    while len(bands) > 2:
        small = np.flatnonzero(np.histogram(ranges, bands)[0] < MISS_BAND_BEAMS)
        if not small.size:
            break
        del bands[max(int(small[-1]), 1)]  # the farthest thin band joins its nearer neighbour (the first, the second)
    return np.asarray(bands)


def match_misses(beams: AngularMixture, density: NPRegDensity, first_range: np.ndarray, edges) -> NPRegDensity:
    """``density`` with its P(no return) scaled per range band so that ``beams`` miss as often as predicted.

    The tables' no-return probabilities are smoothed across states. When they came from the no-returns
    counted at each beam's first occupied cell (before misses were shared among the elements that could have lost them,
    :func:`~mi_lidar.planar.permeable.credited_segments`), a beam could also pass that cell and miss through
    the escape state, so the model predicted more no-returns near the sensor than its training beams had
    and, scaled by one common factor to match the overall rate (Intel: 3.05 % against 2.57 %), far fewer at long range
    (Freiburg 101, first occupied cell 30-40 m: 31 % predicted where 59 % of the training beams missed,
    so far walls stayed solid in sampled scans and hist L1 was 0.31 m). The likelihood is nearly flat in
    such factors (Intel: within 1e-4 nats per beam from 0.8 to 1 in a common one), so they are set by the
    training beams' no-return rate instead, one per range band (``edges``, m, merged by :func:`miss_bands`):
    the states whose range bin centre lies in a band get its factor, and band b's beams (``first_range``,
    (B,) m, the range of each beam's first occupied cell; NaN: none, in no band) then miss at their own
    rate. P(miss) is linear in each factor, so each round sets ``f_b <- f_b (rate_b - P0_b) / (P_b - P0_b)``
    with ``P0_b`` (no table misses, only escapes) and ``P_b`` (the current factors) band b's mean P(miss);
    :data:`MISS_ROUNDS` rounds take up the coupling between bands (a beam that passes its first cell
    meets farther states). Each probability is capped at 1. The escape state (a beam that met no cell)
    is left as it is: its P(null) is counted from its own beams, not smoothed across states (scaled with
    the rest, Edmonton's beams that met no cell were predicted to miss 34 % of the time where 41 % did;
    left, 40 %, test NLL 4.1754 -> 4.1743). Kept only if the mean training score loses less than
    :data:`MISS_TOLERANCE`; otherwise ``density`` is returned unchanged.
    """
    bands = miss_bands(first_range, edges)
    n_bands = bands.size - 1
    band_of = np.clip(np.searchsorted(bands, first_range, side="right") - 1, 0, n_bands - 1)
    band_of = np.where(np.isfinite(first_range), band_of, -1)
    grid = density.grid
    state_band = np.clip(np.searchsorted(bands, grid.state_ranges(), side="right") - 1, 0, n_bands - 1)

    def with_factors(factors: np.ndarray) -> NPRegDensity:
        scaled = np.minimum(density.p_null[: grid.size] * factors[state_band], 1.0)
        return density.with_tables(p_null=np.concatenate([scaled, density.p_null[grid.size :]]))

    def per_band(values: np.ndarray) -> np.ndarray:
        return np.array([values[band_of == b].mean() if np.any(band_of == b) else np.nan for b in range(n_bands)])

    def p_miss(factors: np.ndarray) -> np.ndarray:
        return per_band(beams.p_miss(base_model(with_factors(factors))))

    rate, p0 = per_band((~beams.hit).astype(np.float64)), p_miss(np.zeros(n_bands))
    factors = np.ones(n_bands)
    for _ in range(MISS_ROUNDS):
        p = p_miss(factors)
        ok = np.isfinite(rate) & (p - p0 > 1e-9)
        factors = np.where(ok, factors * np.maximum(rate - p0, 0.0) / np.where(ok, p - p0, 1.0), factors)
    matched = with_factors(factors)
    kept = training_nll(beams, matched) < training_nll(beams, density) + MISS_TOLERANCE
    return matched if kept else density


SHORT_DRAWS = 4  # sampled scans (seeds 0, 1, ...) that count a model's short returns
SHORT_STEPS = 8  # bisection steps of :func:`match_short_returns`


def short_share(z: np.ndarray, hit: np.ndarray, nominal: np.ndarray) -> float:
    """Share of beams that returned more than :data:`FAR` short of their nominal range."""
    return float(np.mean(hit & np.isfinite(nominal) & (z < nominal - FAR)))


def match_short_returns(beams: AngularMixture, trace: PlanarTrace, density: NPRegDensity) -> NPRegDensity:
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
    kept = training_nll(beams, matched) < training_nll(beams, density) + MISS_TOLERANCE
    return matched if kept else density
