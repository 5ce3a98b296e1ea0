"""Observation-level evaluation (thesis 4.3.2, table 4.3).

* mean packet error, eq. 4.3: per packet (``packet`` consecutive firings of one scan, all beams),
  the mean of ||y_j - y^_j|| over true hits (both real and simulated hit), averaged over packets
  that have at least one true hit; rays are shared, so ||y - y^|| = |z - z^|;
* hit precision, recall and F1 (eqs. 4.4-4.6) over all rays;
* symmetric point-cloud error, eq. 4.9, between the real and simulated world clouds.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def asymmetric_pcd_error(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Eq. 4.7: mean distance (m) from each point of ``y_hat`` to its nearest point of ``y``."""
    if len(y) == 0 or len(y_hat) == 0:
        return float("nan")
    d, _ = cKDTree(y).query(y_hat, workers=-1)
    return float(d.mean())


def pcd_error(y: np.ndarray, y_hat: np.ndarray, max_points: int = 300_000, seed: int = 0) -> float:
    """Eq. 4.9: symmetric point-cloud error (m); clouds above ``max_points`` are subsampled at random."""
    rng = np.random.default_rng(seed)
    sub = lambda a: a[rng.choice(len(a), max_points, replace=False)] if len(a) > max_points else a
    y, y_hat = sub(y), sub(y_hat)
    return 0.5 * (asymmetric_pcd_error(y, y_hat) + asymmetric_pcd_error(y_hat, y))


def observation_metrics(
    real: np.ndarray,
    sim: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    packet: int = 32,
    mask: np.ndarray | None = None,
) -> dict:
    """Table 4.3 metrics of simulated ranges against real ones on the same rays.

    Args:
        real, sim: (S, H, W) ranges, m (NaN = miss).
        origins, directions: (S*H*W, 3) world rays (for the point clouds).
        packet: firings per packet.
        mask: optional (S, H, W) bool; only these rays are scored.

    Returns:
        ``packet_error`` (m), ``precision``, ``recall``, ``f1``, ``pcd_error`` (m) and counts.
    """
    s, h, w = real.shape
    if mask is not None:
        real, sim = np.where(mask, real, np.nan), np.where(mask, sim, np.nan)
    rh, sh = np.isfinite(real), np.isfinite(sim)
    true_hit = rh & sh
    n_true, n_false_hit, n_false_miss = int(true_hit.sum()), int((sh & ~rh).sum()), int((rh & ~sh).sum())
    precision = n_true / max(n_true + n_false_hit, 1)
    recall = n_true / max(n_true + n_false_miss, 1)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    err = np.where(true_hit, np.abs(real - sim), 0.0)
    n_pk = int(np.ceil(w / packet))
    pad = n_pk * packet - w
    err_p = np.pad(err, ((0, 0), (0, 0), (0, pad))).reshape(s, h, n_pk, packet).sum(axis=(1, 3))
    cnt_p = np.pad(true_hit, ((0, 0), (0, 0), (0, pad))).reshape(s, h, n_pk, packet).sum(axis=(1, 3))
    packet_error = float(np.mean(err_p[cnt_p > 0] / cnt_p[cnt_p > 0])) if (cnt_p > 0).any() else float("nan")
    pts = lambda r: (origins + directions * r.reshape(-1, 1))[np.isfinite(r.ravel())]
    return {
        "packet_error": packet_error,
        "precision": precision,
        "recall": recall,
        "f1": f1,
        "pcd_error": pcd_error(pts(real), pts(sim)),
        "true_hits": n_true,
        "false_hits": n_false_hit,
        "false_misses": n_false_miss,
    }


def objective(metrics: dict) -> float:
    """Tuning objective of thesis 4.4.1: mean packet error + 2 (1 - F1)."""
    return metrics["packet_error"] + 2.0 * (1.0 - metrics["f1"])
