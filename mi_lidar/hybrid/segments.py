"""Segments and labels: instances from synthetic labels or a simple automatic segmentation.

* :func:`segments_from_labels`: one segment per labelled instance; shrub patches (instance >=
  ``PATCH_BASE``) are cut into square cells of ``patch_cell`` m (thesis fig. 4.12).
* :func:`euclidean_segments`: non-ground points (after ground removal) are voxel-thinned and
  linked when closer than ``radius``; connected components with enough points are segments.
* :class:`SizeClassifier`: nearest class centroid on standardized size features (height,
  major and minor horizontal extent, log point count), trained on labelled segments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mi_lidar.hybrid.classes import OBJECT_CLASSES, PATCH_BASE


@dataclass
class Segment:
    """A group of points forming one object.

    Attributes:
        id: segment id. label: class id. index: (M,) indices into the point array. patch: from a patch.
    """

    id: int
    label: int
    index: np.ndarray
    patch: bool = False


def segments_from_labels(
    points: np.ndarray, labels: np.ndarray, instances: np.ndarray, min_points: int = 20, patch_cell: float = 4.0
) -> list[Segment]:
    """Segments of labelled object instances (classes in ``OBJECT_CLASSES``).

    Args:
        points: (N, 3) m. labels, instances: (N,) per-point class and instance ids.
        min_points: smaller segments are dropped.
        patch_cell: side of the cells patches are cut into, m.
    """
    out = []
    obj = np.isin(labels, OBJECT_CLASSES) & (instances > 0)
    for inst in np.unique(instances[obj]):
        idx = np.nonzero(obj & (instances == inst))[0]
        label = int(np.bincount(labels[idx]).argmax())
        if inst >= PATCH_BASE:
            cells = np.floor(points[idx, :2] / patch_cell).astype(np.int64)
            _, cell_of = np.unique(cells, axis=0, return_inverse=True)
            for c in np.unique(cell_of):
                sub = idx[cell_of.ravel() == c]
                if len(sub) >= min_points:
                    out.append(Segment(int(inst) * 1000 + int(c), label, sub, patch=True))
        elif len(idx) >= min_points:
            out.append(Segment(int(inst), label, idx))
    return out


def euclidean_segments(
    points: np.ndarray, radius: float = 0.5, min_points: int = 20, voxel: float = 0.15
) -> list[Segment]:
    """Connected components of points linked within ``radius`` (m); label 0 (unknown).

    Args:
        points: (N, 3) non-ground points, m.
        radius: link distance, m. min_points: smaller components are dropped. voxel: thinning cell, m.
    """
    if len(points) == 0:
        return []
    keys = np.floor(points / voxel).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    rep = points[first]
    pairs = cKDTree(rep).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(rep), len(rep)))
    _, comp = connected_components(graph, directed=False)
    comp_of_point = comp[inverse.ravel()]
    order = np.argsort(comp_of_point, kind="stable")
    bounds = np.flatnonzero(np.diff(comp_of_point[order])) + 1
    return [Segment(i, 0, grp) for i, grp in enumerate(np.split(order, bounds)) if len(grp) >= min_points]


def segment_features(points: np.ndarray) -> np.ndarray:
    """(4,) height, major and minor horizontal extent (m, from x-y principal axes) and log(count)."""
    xy = points[:, :2] - points[:, :2].mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov(xy.T) if len(points) > 2 else np.eye(2))
    proj = xy @ vecs
    ext = np.sort(proj.max(axis=0) - proj.min(axis=0))[::-1]
    z = points[:, 2]
    return np.array([z.max() - z.min(), ext[0], ext[1], np.log(len(points))])


class SizeClassifier:
    """Nearest class centroid on standardized size features (:func:`segment_features`)."""

    def fit(self, features: np.ndarray, labels: np.ndarray) -> SizeClassifier:
        """Learn centroids from (M, 4) features and (M,) class ids; return self."""
        self.mean, self.std = features.mean(axis=0), features.std(axis=0) + 1e-9
        z = (features - self.mean) / self.std
        self.classes = np.unique(labels)
        self.centroids = np.stack([z[labels == c].mean(axis=0) for c in self.classes])
        return self

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(M,) predicted class ids of (M, 4) features."""
        z = (np.atleast_2d(features) - self.mean) / self.std
        d = np.linalg.norm(z[:, None] - self.centroids[None], axis=2)
        return self.classes[d.argmin(axis=1)]


def majority_label(segment: Segment, labels: np.ndarray) -> int:
    """Most frequent true class among a segment's points."""
    return int(np.bincount(labels[segment.index]).argmax())
