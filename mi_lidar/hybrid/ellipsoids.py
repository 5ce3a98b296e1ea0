"""Non-ground elements: top-down hierarchical k-means into Gaussian ellipsoids (thesis 4.3.1.2).

All points start in one cluster. Each round splits, in order of decreasing sum of squared
errors (SSE), as many clusters as are still needed to reach ``n_clusters`` (all of them while the
target is far). A split is 2-means (branching factor 2) started from the cluster mean plus and
minus its principal standard deviation, refined by ``iterations`` Lloyd steps; it is kept only if
both children hold at least ``min_points`` points, else the cluster becomes a leaf. The
per-round work is vectorised over clusters, so a round costs O(N). The result equals cutting the
dendrogram at the requested count, greedily by SSE. Each cluster gives an ellipsoid with the
sample mean and covariance (1 / (M - 1) normalisation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_lidar.hybrid.model import EllipsoidSet


@dataclass
class ClusterParams:
    """Ellipsoid fitting parameters (thesis table 4.1).

    Attributes:
        clusters_per_point: requested clusters = ceil(clusters_per_point * N).
        min_points: minimum points per cluster.
        iterations: Lloyd iterations per split.
        min_sigma: floor on the principal standard deviations, m.
    """

    clusters_per_point: float = 0.042
    min_points: int = 5
    iterations: int = 4
    min_sigma: float = 0.02


def _cluster_stats(points: np.ndarray, labels: np.ndarray, n: int):
    count = np.bincount(labels, minlength=n).astype(float)
    mean = (
        np.stack([np.bincount(labels, points[:, i], minlength=n) for i in range(3)], 1) / np.maximum(count, 1)[:, None]
    )
    d = points - mean[labels]
    outer = d[:, :, None] * d[:, None, :]
    second = np.stack([np.bincount(labels, outer[:, i, j], minlength=n) for i in range(3) for j in range(3)], 1)
    return count, mean, second.reshape(n, 3, 3)


def hierarchical_kmeans(points: np.ndarray, n_clusters: int, min_points: int = 5, iterations: int = 4) -> np.ndarray:
    """Top-down hierarchical 2-means labels.

    Args:
        points: (N, 3) m.
        n_clusters: requested number of clusters.
        min_points: minimum points per cluster.
        iterations: Lloyd iterations per split.

    Returns:
        (N,) int64 cluster label in ``[0, C)`` with ``C <= n_clusters``.
    """
    n = len(points)
    labels = np.zeros(n, np.int64)
    if n == 0:
        return labels
    n_cur = 1
    frozen = np.zeros(1, bool)
    while n_cur < n_clusters:
        count, mean, scatter = _cluster_stats(points, labels, n_cur)
        sse = np.trace(scatter, axis1=1, axis2=2)
        candidate = (~frozen) & (count >= 2 * min_points) & (sse > 0)
        order = np.argsort(-np.where(candidate, sse, -1))
        split = order[: min(int(candidate.sum()), n_clusters - n_cur)]
        if len(split) == 0:
            break
        # ---- 2-means of every cluster in ``split`` at once
        slot = np.full(n_cur, -1)
        slot[split] = np.arange(len(split))
        member = slot[labels] >= 0
        idx = np.nonzero(member)[0]
        s_of = slot[labels[idx]]
        w, v = np.linalg.eigh(scatter[split] / np.maximum(count[split] - 1, 1)[:, None, None])
        step = v[:, :, 2] * np.sqrt(np.maximum(w[:, 2], 0))[:, None]
        centers = np.stack([mean[split] - step, mean[split] + step], 1)  # (s, 2, 3)
        p = points[idx]
        for _ in range(iterations):
            d0 = np.sum((p - centers[s_of, 0]) ** 2, axis=1)
            d1 = np.sum((p - centers[s_of, 1]) ** 2, axis=1)
            side = (d1 < d0).astype(np.int64)
            key = 2 * s_of + side
            cnt = np.bincount(key, minlength=2 * len(split)).astype(float)
            sums = np.stack([np.bincount(key, p[:, i], minlength=2 * len(split)) for i in range(3)], 1)
            new = (sums / np.maximum(cnt, 1)[:, None]).reshape(-1, 2, 3)
            centers = np.where((cnt.reshape(-1, 2) > 0)[:, :, None], new, centers)
        cnt = cnt.reshape(-1, 2)
        ok = cnt.min(axis=1) >= min_points
        frozen[split[~ok]] = True
        accepted = split[ok]
        new_id = np.full(len(split), -1)
        new_id[ok] = n_cur + np.arange(ok.sum())
        move = member.copy()
        move[idx] = (side == 1) & ok[s_of]
        labels[move] = new_id[slot[labels[move]]]
        frozen = np.r_[frozen, np.zeros(len(accepted), bool)]
        n_cur += len(accepted)
    return labels


def fit_ellipsoids(points: np.ndarray, params: ClusterParams) -> tuple[EllipsoidSet, np.ndarray]:
    """Cluster non-ground points and fit one Gaussian per cluster.

    Args:
        points: (N, 3) m.
        params: clustering parameters.

    Returns:
        The ellipsoids (attributes at defaults) and the (N,) element index of every point (-1 for
        points of clusters below ``min_points``).
    """
    if len(points) < params.min_points:
        return EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))), np.full(len(points), -1)
    target = max(1, int(np.ceil(params.clusters_per_point * len(points))))
    labels = hierarchical_kmeans(points, target, params.min_points, params.iterations)
    n = labels.max() + 1
    count, mean, scatter = _cluster_stats(points, labels, n)
    keep = count >= params.min_points
    remap = np.full(n, -1)
    remap[keep] = np.arange(keep.sum())
    cov = scatter[keep] / (count[keep] - 1)[:, None, None]
    w, v = np.linalg.eigh(cov)
    cov = np.einsum("nij,nj,nkj->nik", v, np.maximum(w, params.min_sigma**2), v)
    return EllipsoidSet(mean[keep], cov), remap[labels]
