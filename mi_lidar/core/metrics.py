"""Observation-level losses (thesis ch. 2.3): a model's score beside the realism of its samples, per ray.

Every report that prints an NLL also samples the same model at the same rays and prints
:func:`metrics_of`: a model that wins the likelihood by spreading its mass is caught at once.
"""

from __future__ import annotations

import numpy as np


def cdf_l1(a: np.ndarray, b: np.ndarray) -> float:
    """L1 distance between the empirical CDFs of samples ``a`` and ``b`` (their units, m)."""
    if a.size == 0 or b.size == 0:
        return float("nan")
    grid = np.sort(np.concatenate([a, b]))
    fa = np.searchsorted(np.sort(a), grid, side="right") / a.size
    fb = np.searchsorted(np.sort(b), grid, side="right") / b.size
    return float(np.sum(np.abs(fa - fb)[:-1] * np.diff(grid)))


def metrics_of(
    ll: np.ndarray, measured: np.ndarray, hit: np.ndarray, sim_range: np.ndarray, sim_hit: np.ndarray
) -> dict:
    """NLL beside the realism of one sampled scan, per ray (numpy arrays of equal length).

    Returns:
        ``rays``; ``nll`` and ``nll_median`` (nats per ray, the one score); the measured and simulated
        return rates; ``range_error_mean``/``_median``/``_p90``: |measured - sampled| range where both
        returned (m); hit/miss ``precision``, ``recall`` and ``f1`` of sampled returns against measured
        ones; ``histogram_l1``: L1 distance between the CDFs of measured and sampled ranges (m).
    """
    both = hit & sim_hit
    err = np.abs(measured[both] - sim_range[both])
    tp, fp, fn = int(np.sum(hit & sim_hit)), int(np.sum(~hit & sim_hit)), int(np.sum(hit & ~sim_hit))
    precision = tp / (tp + fp) if tp + fp else float("nan")
    recall = tp / (tp + fn) if tp + fn else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if tp else float("nan")
    nan = float("nan")
    return {
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
