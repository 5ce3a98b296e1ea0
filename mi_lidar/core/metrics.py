"""Observation-level losses (thesis ch. 2.3): a model's score beside the realism of its samples, per ray.

Every report that prints an NLL also samples the same model at the same rays and prints
:func:`metrics_of`: a model that wins the likelihood by spreading its mass is caught at once.
:func:`worse_samples` says which realism measures a change of model made worse.

A note on the paired range error (``range_error_median``, ``_p90``: |measured - sampled| ray by
ray). It rewards models that sample less spread than the sensor: a model that samples the exact
distribution of the measured residual has a paired error about sqrt(2) times the residual's own
(two independent draws), while a deterministic model that returns the mean has 1 times. On the shared
Ouster frame an oracle that samples the empirical residual of the range-image mesh (binned by state)
has a paired median 35 % above the bare mesh's. The distribution-level measures (histogram match,
hit/miss F1, Chamfer distance and its stray half) have no such bias; :func:`worse_samples` judges by those by default.

A paired measure that has no such bias either: the continuous ranked probability score
(:func:`crps`, ``crps_mean`` and ``crps_median`` of :func:`metrics_of`), estimated from several
sampled scans at the same rays. It is a proper scoring rule (its expectation is smallest for the
sensor's own distribution), equals |point - measured| for a deterministic model, and is in metres.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.errors import ParameterError


def cdf_l1(a: np.ndarray, b: np.ndarray) -> float:
    """L1 distance between the empirical CDFs of samples ``a`` and ``b`` (their units, m)."""
    if a.size == 0 or b.size == 0:
        return float("nan")
    grid = np.sort(np.concatenate([a, b]))
    fa = np.searchsorted(np.sort(a), grid, side="right") / a.size
    fb = np.searchsorted(np.sort(b), grid, side="right") / b.size
    return float(np.sum(np.abs(fa - fb)[:-1] * np.diff(grid)))


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric point-cloud error (Chamfer distance): the mean of the mean distances (m) from each
    point of ``a`` (P, 3) to the nearest point of ``b`` (Q, 3) and from ``b`` to ``a``; NaN when one is empty."""
    return float(np.mean(chamfer_halves(a, b)))


def chamfer_halves(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The two halves of :func:`chamfer`: mean distance (m) from ``a`` to ``b`` and from ``b`` to ``a``."""
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return float("nan"), float("nan")
    return float(cKDTree(b).query(a)[0].mean()), float(cKDTree(a).query(b)[0].mean())


def crps(
    measured: np.ndarray,
    hit: np.ndarray,
    draws_range: np.ndarray,
    draws_hit: np.ndarray,
    no_return: float,
    fair: bool = True,
) -> np.ndarray:
    """The continuous ranked probability score of ``M`` sampled scans against the measured one, per ray (m).

    For each ray, with ``y`` its measurement and ``s_1..s_M`` its samples,
    ``CRPS = mean_i |s_i - y| - sum_ij |s_i - s_j| / (2 M (M - 1))``: the *fair* estimator, whose
    expectation is the CRPS of the model's distribution itself, so that it is smallest in expectation
    for the sensor's own distribution whatever ``M``. ``fair=False`` divides by ``2 M^2`` instead (the
    CRPS of the ``M`` samples' empirical distribution): that estimator is biased upwards by
    ``E|S - S'| / (2M)`` and so rewards narrow models (at ``M = 8`` it is smallest, for Gaussian truth,
    for a model 21 % narrower than the truth). Both equal ``|s - y|`` for a deterministic model.

    A no-return is represented by the value ``no_return`` on both sides (the sensor's no-return code,
    e.g. 81.83 m): a range is a number on one line, a miss the code at its top, as the sensor writes
    it. A miss drawn where the sensor returned at ``y`` (or the reverse) costs ``no_return - y``; the
    score is then dominated by such beams and is read per beam (mean and median), not as a range error.

    Args:
        measured, hit: (N,) measured ranges (m; any value where ``hit`` is False) and return flags.
        draws_range, draws_hit: (M, N) sampled ranges (m) and return flags, ``M >= 2``.
        no_return: the value (m) that stands for a no-return on both sides.
        fair: the fair estimator (default) or the empirical distribution's (see above).

    Returns:
        (N,) CRPS per ray, m.

    Raises:
        ParameterError: fewer than 2 sampled scans.
    """
    samples = np.where(draws_hit, draws_range, no_return).astype(np.float64)
    m = samples.shape[0]
    if m < 2:
        raise ParameterError(f"crps: needs at least 2 sampled scans per ray (draws of shape (M, N)); got M = {m}")
    y = np.where(hit, measured, no_return).astype(np.float64)
    error = np.mean(np.abs(samples - y), axis=0)
    ordered = np.sort(samples, axis=0)
    rank = np.arange(m, dtype=np.float64)[:, None]
    spread = 2.0 * np.sum((2.0 * rank - m + 1.0) * ordered, axis=0)  # sum over all i, j of |s_i - s_j|
    return error - spread / (2.0 * m * (m - 1) if fair else 2.0 * m * m)


REALISM = ("histogram_l1", "f1", "chamfer", "stray")  # distribution-level realism measures :func:`worse_samples` checks
HIGHER_IS_BETTER = ("f1", "precision", "recall")


def worse_samples(before: dict, after: dict, tolerance: float = 0.1, keys: tuple[str, ...] = REALISM) -> dict:
    """The sample-realism measures that got worse by more than ``tolerance`` (relative) from ``before`` to ``after``.

    Args:
        before, after: rows of :func:`metrics_of` (``chamfer`` when present).
        tolerance: relative change allowed (0.1: 10 %).
        keys: measures to check (those missing from either row are skipped).

    Returns:
        ``{measure: (before, after)}`` of every measure that got worse; empty when none did. Diagnosis
        and development paths use it to flag an effect that improves the NLL by spreading its mass.
    """
    out = {}
    for key in keys:
        a, b = before.get(key), after.get(key)
        if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)):
            continue
        worse = b < a * (1 - tolerance) if key in HIGHER_IS_BETTER else b > a * (1 + tolerance) + 1e-12
        if worse:
            out[key] = (float(a), float(b))
    return out


def metrics_of(
    ll: np.ndarray,
    measured: np.ndarray,
    hit: np.ndarray,
    sim_range: np.ndarray,
    sim_hit: np.ndarray,
    origins: np.ndarray | None = None,
    directions: np.ndarray | None = None,
    draws: tuple[np.ndarray, np.ndarray] | None = None,
    no_return: float | None = None,
) -> dict:
    """NLL beside the realism of one sampled scan, per ray (numpy arrays of equal length).

    Args:
        ll: (N,) scored log-likelihood of the measurements, nats.
        measured, hit: (N,) measured ranges (m) and return flags.
        sim_range, sim_hit: (N,) one sampled range (m) and return flag per ray.
        origins, directions: optional (N, 3) ray origins (m) and unit directions in one frame; with
            them the Chamfer distance between the measured and the sampled point clouds is added.
        draws: optional (M, N) sampled ranges (m) and (M, N) return flags of ``M >= 2`` sampled scans
            at the same rays (the one of ``sim_range`` may be among them); with them and ``no_return``
            (the value, m, that stands for a no-return: :func:`crps`) the CRPS is added, and the histogram
            distance of every sampled scan.

    Returns:
        ``rays``; ``nll`` and ``nll_median`` (nats per ray, the one score); the measured and simulated
        return rates; ``range_error_mean``/``_median``/``_p90``: |measured - sampled| range where both
        returned (m); hit/miss ``precision``, ``recall`` and ``f1`` of sampled returns against measured
        ones; ``histogram_l1``: L1 distance between the CDFs of measured and sampled ranges (m);
        ``chamfer`` (m, with rays): :func:`chamfer` of the measured and sampled points, and ``stray``
        (m): its half from the sampled points to the measured ones (how far sampled points stray from
        what the sensor saw: outliers drawn anywhere raise it, samples on the real surfaces do not);
        ``crps_mean`` and ``crps_median`` (m, with draws): the mean and median over rays of :func:`crps`;
        ``histogram_l1_draws`` (m, with draws): ``histogram_l1`` averaged over the ``M`` sampled scans (one
        scan's varies with its draw: 0.15-0.29 m between draws of one model on the Freiburg campus log,
        whose sampled beams share their errors along each scan); ``histogram_l1_draws_se`` and
        ``crps_mean_se`` (m, with draws): the standard errors of those means and of ``crps_mean`` that come
        from the draws (:func:`crps_mean_se`): two models whose figures differ by less than about twice
        them are not told apart by these draws.
    """
    both = hit & sim_hit
    err = np.abs(measured[both] - sim_range[both])
    tp, fp, fn = int(np.sum(hit & sim_hit)), int(np.sum(~hit & sim_hit)), int(np.sum(hit & ~sim_hit))
    precision = tp / (tp + fp) if tp + fp else float("nan")
    recall = tp / (tp + fn) if tp + fn else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if tp else float("nan")
    nan = float("nan")
    out = {
        "rays": int(ll.size),
        "nll": float(-np.mean(ll)) if ll.size else nan,
        "nll_median": float(-np.median(ll)) if ll.size else nan,
        "hit_rate_measured": float(hit.mean()) if hit.size else nan,
        "hit_rate_simulated": float(sim_hit.mean()) if sim_hit.size else nan,
        "range_error_mean": float(err.mean()) if err.size else nan,
        "range_error_median": float(np.median(err)) if err.size else nan,
        "range_error_p90": float(np.quantile(err, 0.9)) if err.size else nan,
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "histogram_l1": cdf_l1(measured[hit], sim_range[sim_hit]),
    }
    if origins is not None and directions is not None:
        missed, stray = chamfer_halves(
            origins[hit] + measured[hit, None] * directions[hit],
            origins[sim_hit] + sim_range[sim_hit, None] * directions[sim_hit],
        )
        out["chamfer"], out["stray"] = 0.5 * (missed + stray), stray
    if draws is not None:
        if no_return is None:
            raise ParameterError("metrics_of: draws need no_return, the value (m) that stands for a no-return")
        per_ray = crps(measured, hit, draws[0], draws[1], no_return)
        out["crps_mean"] = float(per_ray.mean()) if per_ray.size else nan
        out["crps_median"] = float(np.median(per_ray)) if per_ray.size else nan
        out["crps_mean_se"] = crps_mean_se(measured, hit, draws, no_return) if per_ray.size else nan
        l1 = np.array([cdf_l1(measured[hit], z[h]) for z, h in zip(*draws)])
        out["histogram_l1_draws"] = float(np.mean(l1))
        out["histogram_l1_draws_se"] = float(np.std(l1, ddof=1) / np.sqrt(l1.size))
    return out


def crps_mean_se(measured: np.ndarray, hit: np.ndarray, draws: tuple, no_return: float) -> float:
    """The standard error (m) of the mean :func:`crps` that comes from drawing ``M`` scans (``draws``, (M, N) each),
    by the jackknife over the draws: ``sqrt((M - 1) / M * sum_k (c_k - c)^2)`` with ``c_k`` the mean CRPS of the
    draws without draw ``k`` and ``c`` their mean. A third draw at least is needed (else NaN); the fair estimator
    is unbiased whatever ``M``, so the means left out estimate the same CRPS."""
    m = draws[0].shape[0]
    if m < 3:
        return float("nan")
    keep = [np.arange(m) != k for k in range(m)]
    left_out = np.array([crps(measured, hit, draws[0][k], draws[1][k], no_return).mean() for k in keep])
    return float(np.sqrt((m - 1) / m * np.sum((left_out - left_out.mean()) ** 2)))
