"""Line detection in planar scans by split-and-merge, scored against the walls of the map.

:func:`split_and_merge` breaks a scan (points in beam order) where consecutive points are farther apart
than ``gap``, splits each run recursively at its point farthest from the chord while that distance
exceeds ``split``, keeps the pieces of at least ``min_points`` points as total-least-squares segments,
and merges neighbours whose joint fit stays within ``split``.

The reference does not come from any detector: the walls are found in the whole-log map
(:func:`~mi_lidar.apps.walls.map_walls`) and a state's reference is the pieces of them its nominal scan
(the ideal ray cast in its leave-out map) sees over at least ``min_beams`` (5) consecutive beams
(:func:`~mi_lidar.apps.walls.visible_walls`). A detected segment matches a wall piece
(:func:`match_segments`) when their directions differ by less than 10 deg, its midpoint lies within
0.15 m of the piece's line and projects onto the piece (0.25 m of slack); matching is one to one. The
application runs on the protocol's test scans only (no simulator was fitted on them), each simulated
dataset's every sampled scan.

==============  ==================================================  ====
alpha           meaning                                             unit
==============  ==================================================  ====
``split``       split / merge distance threshold                    m
``min_points``  smallest segment kept                               -
``gap``         largest distance between neighbours of one run      m
==============  ==================================================  ====

``J``: detection error, ``1 - F1`` of the matches, averaged over the test states that see a wall piece
(and over a simulator's sampled datasets). Also reported: precision, recall and the detections per scan.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from mi_lidar.apps.risk import Parameter
from mi_lidar.apps.scans import PlanarStates, relative, scan_points
from mi_lidar.apps.walls import visible_walls

MATCH_ANGLE = np.radians(10.0)
MATCH_OFFSET = 0.15  # m
MATCH_SLACK = 0.25  # m


def fit_segment(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The total-least-squares segment (4,) ``x0, y0, x1, y1`` of (n, 2) ordered points, and its largest residual, m."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    direction = vt[0]
    t = (points - centre) @ direction
    residual = float(np.max(np.abs((points - centre) @ vt[1]))) if len(points) > 2 else 0.0
    return np.concatenate([centre + t[0] * direction, centre + t[-1] * direction]), residual


def _split(points: np.ndarray, split: float) -> list[tuple[int, int]]:
    """Index ranges ``[a, b]`` (inclusive) of the pieces of one run."""
    pieces, stack = [], [(0, len(points) - 1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            pieces.append((a, b))
            continue
        chord = points[b] - points[a]
        length = np.hypot(*chord)
        rel = points[a : b + 1] - points[a]
        distance = np.abs(chord[0] * rel[:, 1] - chord[1] * rel[:, 0]) / length if length > 0 else np.hypot(*rel.T)
        k = int(np.argmax(distance))
        if distance[k] > split and 0 < k < b - a:
            stack += [(a + k, b), (a, a + k)]
        else:
            pieces.append((a, b))
    return sorted(pieces)


def split_and_merge(points: np.ndarray, split: float, min_points: int, gap: float) -> np.ndarray:
    """(L, 4) segments ``x0, y0, x1, y1`` (m) found in (n, 2) points in beam order (see the module docstring)."""
    if len(points) < 2:
        return np.zeros((0, 4))
    breaks = np.flatnonzero(np.hypot(*np.diff(points, axis=0).T) > gap) + 1
    segments = []
    for run in np.split(points, breaks):
        pieces = [run[a : b + 1] for a, b in _split(run, split) if b - a + 1 >= min_points]
        merged: list[np.ndarray] = []
        for piece in pieces:
            if merged:
                joint = np.concatenate([merged[-1], piece])
                if fit_segment(joint)[1] <= split:
                    merged[-1] = joint
                    continue
            merged.append(piece)
        segments += [fit_segment(p)[0] for p in merged]
    return np.asarray(segments).reshape(-1, 4)


def match_segments(detected: np.ndarray, walls: np.ndarray) -> int:
    """Number of one-to-one matches between (D, 4) detected segments and (W, 4) walls (see the module docstring)."""
    if len(detected) == 0 or len(walls) == 0:
        return 0
    d_dir = detected[:, 2:] - detected[:, :2]
    w_dir = walls[:, 2:] - walls[:, :2]
    w_len = np.maximum(np.hypot(*w_dir.T), 1e-9)
    w_unit = w_dir / w_len[:, None]
    cos = np.abs(d_dir @ w_unit.T) / np.maximum(np.hypot(*d_dir.T), 1e-9)[:, None]
    mid = 0.5 * (detected[:, :2] + detected[:, 2:])
    rel = mid[:, None, :] - walls[None, :, :2]
    along = np.sum(rel * w_unit[None], axis=-1)
    offset = np.abs(rel[..., 0] * w_unit[None, :, 1] - rel[..., 1] * w_unit[None, :, 0])
    ok = (cos > np.cos(MATCH_ANGLE)) & (offset < MATCH_OFFSET)
    ok &= (along > -MATCH_SLACK) & (along < w_len[None] + MATCH_SLACK)
    cost = np.where(ok, offset, np.inf)
    matches = 0
    while np.isfinite(cost).any():
        i, j = np.unravel_index(np.argmin(cost), cost.shape)
        matches += 1
        cost[i, :] = np.inf
        cost[:, j] = np.inf
    return matches


@dataclass
class LineDetection:
    """The line detection application (see the module docstring).

    Attributes:
        min_beams: a wall piece seen by fewer consecutive nominal beams is not in the reference.
    """

    min_beams: int = 5
    sweep: ClassVar[str] = "split"  # the parameter swept at the best real setting (thesis fig. 3.20)
    effort: ClassVar[str] = "detections"  # the metric shown beside J along the sweep
    name: str = "lines"
    objective: str = "line detection error, 1 - F1 against the map's walls"
    parameters: tuple[Parameter, ...] = (
        Parameter("split", (0.01, 0.02, 0.05, 0.1, 0.2, 0.4), start=0.01, unit="m"),
        Parameter("min_points", (3.0, 5.0, 8.0, 12.0, 20.0), start=3.0),
        Parameter("gap", (0.1, 0.2, 0.3, 0.5, 1.0, 2.0), start=2.0, unit="m"),
    )

    def walls(self, states: PlanarStates, t: int) -> np.ndarray:
        """(V, 4) the wall pieces state ``t`` sees, in the laser frame (built once per state)."""

        def build() -> np.ndarray:
            pieces = visible_walls(states.walls, states.poses[t], states.nominal[t], states.angles, self.min_beams)
            ends = [relative(states.poses[t], np.c_[pieces[:, k : k + 2], np.zeros(len(pieces))]) for k in (0, 2)]
            return np.concatenate([e[:, :2] for e in ends], axis=1)

        return states.memo(("walls", self.min_beams, t), build)

    def evaluate(self, alpha: dict, states: PlanarStates, ranges: np.ndarray) -> dict:
        """Detect lines in every test scan of ``ranges`` ((S, T, N) or (T, N)) with setting ``alpha``."""
        data = ranges if np.ndim(ranges) == 3 else np.asarray(ranges)[None]
        per_set, precision, recall, counts = [], [], [], []
        for scans in data:
            f1 = []
            for t in np.flatnonzero(states.test):
                walls = self.walls(states, t)
                if len(walls) == 0:
                    continue
                found = split_and_merge(
                    scan_points(scans[t], states.angles), alpha["split"], int(alpha["min_points"]), alpha["gap"]
                )
                matched = match_segments(found, walls)
                p = matched / len(found) if len(found) else 0.0
                r = matched / len(walls)
                precision.append(p)
                recall.append(r)
                f1.append(2 * p * r / (p + r) if p + r else 0.0)
                counts.append(len(found))
            per_set.append(1.0 - float(np.mean(f1)) if f1 else float("nan"))
        return {
            "J": float(np.mean(per_set)),
            "J_runs": per_set,
            "precision": float(np.mean(precision)) if precision else float("nan"),
            "recall": float(np.mean(recall)) if recall else float("nan"),
            "detections": float(np.mean(counts)) if counts else float("nan"),
        }
