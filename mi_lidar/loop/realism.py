"""Realism beside likelihood: a model's held-out NLL next to how one scan sampled from it compares with the log.

A model can win the likelihood by spreading its mass (a large share of outliers, say), and then the
scans sampled from it look nothing like the sensor's. :class:`Realism` keeps, for one model, the
held-out per-ray scores and one sampled scan at the same rays with
:func:`~mi_lidar.core.metrics.metrics_of` (median and p90 |range error|, return rates, hit/miss F1,
histogram distance); :func:`realism_warning` says when a change of model makes the samples clearly
worse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

HISTOGRAM_WORSE = 0.5  # a joined effect that raises the histogram distance by half (and 1 cm) ...
RATE_WORSE = 0.02  # ... or moves the sampled return rate 2 points further from the measured one ...
ERROR_WORSE = 1.5  # ... or multiplies the median and p90 |range error| by 1.5 without a better histogram


@dataclass
class Realism:
    """A model's held-out score beside the realism of one sampled scan at the held-out rays.

    Attributes:
        model: what the row is (``given model``, ``+ effect``, ``final model``).
        metrics: :func:`~mi_lidar.core.metrics.metrics_of` (NLL, |range error|, return rates, F1, histogram).
        warning: why the samples are clearly worse than the previous row's ('' when they are not).
        ll: (N,) held-out per-ray log-likelihood, nats.
        sim_range, sim_hit: (N,) the sampled scan (m, NaN for a miss) and its returns.
    """

    model: str
    metrics: dict
    warning: str = ""
    ll: np.ndarray = field(repr=False, default=None)
    sim_range: np.ndarray = field(repr=False, default=None)
    sim_hit: np.ndarray = field(repr=False, default=None)

    def row(self) -> dict:
        return {"model": self.model, **self.metrics, "warning": self.warning}


def realism_warning(label: str, before: dict, after: dict) -> str:
    """Why the samples of ``after`` are clearly worse than those of ``before`` ('' when they are not).

    A one-draw |range error| grows when a missing noise law is added (the samples spread as the
    sensor does), so it only counts with a histogram that is no better; the histogram distance and
    the return rate are distribution-level and cannot get worse for an effect that is right.
    """
    reasons = []
    if after["histogram_l1"] > (1.0 + HISTOGRAM_WORSE) * before["histogram_l1"] + 0.01:
        reasons.append(
            f"the histogram distance grows from {before['histogram_l1']:.3f} to {after['histogram_l1']:.3f} m"
        )
    rate = after["hit_rate_measured"]
    if abs(after["hit_rate_simulated"] - rate) > abs(before["hit_rate_simulated"] - rate) + RATE_WORSE:
        reasons.append(
            f"the sampled return rate moves from {before['hit_rate_simulated']:.3f} to "
            f"{after['hit_rate_simulated']:.3f} (measured {rate:.3f})"
        )
    errors = ("range_error_median", "range_error_p90")
    if after["histogram_l1"] >= before["histogram_l1"] and all(
        after[k] > ERROR_WORSE * before[k] for k in errors if math.isfinite(before[k])
    ):
        reasons.append(
            f"the median / p90 |range error| of samples grow from {before['range_error_median']:.3f} / "
            f"{before['range_error_p90']:.3f} to {after['range_error_median']:.3f} / {after['range_error_p90']:.3f} m"
        )
    if not reasons:
        return ""
    return f"{label} lowers the held-out NLL but its samples look less like the sensor: " + "; ".join(reasons) + "."
