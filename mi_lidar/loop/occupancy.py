"""Leave-out hit/pass-through maps of a planar log, on a regular 2D grid.

A planar scan contributes to every grid cell it touches: the cell of each return's end point
gains a *hit* (and the point's first and second moments), and each cell a beam crosses before
its end point (for a miss: before it leaves the grid) gains a *pass-through*. These are the
counts of the thesis's counting estimate ``p_hit = hits / (hits + pass-throughs)``.

Contributions are additive over scans, so the map that leaves out a set of scans is the total
minus their contributions: :meth:`CountMap.leave_out` builds it exactly in time proportional to
the scans left out, and :func:`count_scans` recomputes any subset from scratch (the leak check).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.log import Log

MOMENTS = ("n_hit", "n_pass", "sx", "sy", "sxx", "sxy", "syy")


@dataclass(frozen=True)
class Grid:
    """A regular 2D grid in the world plane.

    Attributes:
        origin: (2,) world position (m) of the lower corner of cell (0, 0).
        cell: cell size, m.
        shape: (nx, ny) number of cells along x and y.
    """

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]

    @classmethod
    def around(cls, points: np.ndarray, cell: float, margin: float = 1.0) -> Grid:
        """The grid covering (N, 2) ``points`` (m) plus ``margin`` (m) on every side."""
        if cell <= 0:
            raise ParameterError(f"grid: cell={cell} m must be > 0, e.g. 0.05")
        lo = points.min(axis=0) - margin
        hi = points.max(axis=0) + margin
        shape = tuple(int(v) for v in np.ceil((hi - lo) / cell))
        return cls(origin=(float(lo[0]), float(lo[1])), cell=float(cell), shape=shape)

    @property
    def size(self) -> int:
        """Number of cells."""
        return self.shape[0] * self.shape[1]

    def index(self, ij: np.ndarray) -> np.ndarray:
        """Flat indices of (N, 2) integer cell coordinates; -1 outside the grid."""
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < self.shape[0]) & (ij[:, 1] >= 0) & (ij[:, 1] < self.shape[1])
        return np.where(inside, ij[:, 0] * self.shape[1] + ij[:, 1], -1)

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """Flat cell index of (N, 2) world points (m); -1 outside the grid."""
        ij = np.floor((xy - np.asarray(self.origin)) / self.cell).astype(np.int64)
        return self.index(ij)

    def center(self, flat: np.ndarray) -> np.ndarray:
        """(N, 2) world centers (m) of flat cell indices."""
        ij = np.stack([flat // self.shape[1], flat % self.shape[1]], axis=-1)
        return np.asarray(self.origin) + (ij + 0.5) * self.cell

    def exit_distance(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """(N,) distance (m) along unit (N, 2) rays from (N, 2) origins inside the grid to its boundary."""
        lo = np.asarray(self.origin)
        hi = lo + np.asarray(self.shape) * self.cell
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(
                direction > 0, (hi - origin) / direction, np.where(direction < 0, (lo - origin) / direction, np.inf)
            )
        return np.maximum(t.min(axis=1), 0.0)


def ray_cells(
    grid: Grid, origin: np.ndarray, direction: np.ndarray, length: np.ndarray, step: float, dilate: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Cells each ray crosses on ``[0, length)``, sampled every ``step``.

    Args:
        grid: the grid.
        origin, direction: (N, 2) ray origins (m) and unit directions.
        length: (N,) ray lengths, m.
        step: sampling step along the rays (m); a quarter of a cell misses only corner clips.
        dilate: also return the cells within this many cells (Chebyshev) of a crossed cell.

    Returns:
        ``(ray, cell)``: unique (ray index, flat cell index) pairs, sorted by ray.
    """
    count = np.maximum(np.ceil(length / step).astype(np.int64), 0)
    ray = np.repeat(np.arange(len(count)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    t = (np.arange(ray.size) - first) * step
    ij = np.floor((origin[ray] + t[:, None] * direction[ray] - np.asarray(grid.origin)) / grid.cell).astype(np.int64)
    if dilate > 0:
        offsets = np.stack(np.meshgrid(np.arange(-dilate, dilate + 1), np.arange(-dilate, dilate + 1)), -1).reshape(
            -1, 2
        )
        key = np.unique(ray * grid.size + np.maximum(grid.index(ij), 0))  # thin the samples first
        ray, flat = key // grid.size, key % grid.size
        ij = np.stack([flat // grid.shape[1], flat % grid.shape[1]], -1)
        ray = np.repeat(ray, len(offsets))
        ij = (ij[:, None, :] + offsets[None]).reshape(-1, 2)
    flat = grid.index(ij)
    keep = flat >= 0
    key = np.unique(ray[keep] * grid.size + flat[keep])
    return key // grid.size, key % grid.size


@dataclass
class ScanCounts:
    """Per-scan contributions to the map, concatenated over scans.

    Attributes:
        grid: the grid.
        hit_start: (S + 1,) offsets of each scan's returns in ``hit_cell`` / ``hit_xy``.
        hit_cell: (Nh,) flat cell of each return's end point (-1 outside the grid).
        hit_xy: (Nh, 2) end points, m.
        pass_start: (S + 1,) offsets of each scan's pass-throughs in ``pass_cell``.
        pass_cell: (Np,) flat cells crossed before the end point (one entry per beam and cell).
    """

    grid: Grid
    hit_start: np.ndarray
    hit_cell: np.ndarray
    hit_xy: np.ndarray
    pass_start: np.ndarray
    pass_cell: np.ndarray

    @property
    def n_scans(self) -> int:
        return len(self.hit_start) - 1

    def moments(self, scans: np.ndarray) -> dict[str, np.ndarray]:
        """Dense per-cell sums (:data:`MOMENTS`) of the contributions of ``scans``."""
        scans = np.asarray(scans, dtype=np.int64)
        size = self.grid.size
        take = lambda start: (
            np.concatenate([np.arange(start[s], start[s + 1]) for s in scans]) if len(scans) else np.zeros(0, np.int64)
        )  # noqa: E731
        hits, passes = take(self.hit_start), take(self.pass_start)
        cell, xy = self.hit_cell[hits], self.hit_xy[hits]
        keep = cell >= 0
        cell, xy = cell[keep], xy[keep] - self.grid.center(cell[keep])  # moments about the cell center
        out = {
            "n_hit": np.bincount(cell, minlength=size).astype(np.float64),
            "n_pass": np.bincount(self.pass_cell[passes], minlength=size).astype(np.float64),
        }
        for name, w in (
            ("sx", xy[:, 0]),
            ("sy", xy[:, 1]),
            ("sxx", xy[:, 0] ** 2),
            ("sxy", xy[:, 0] * xy[:, 1]),
            ("syy", xy[:, 1] ** 2),
        ):
            out[name] = np.bincount(cell, weights=w, minlength=size)
        return out


def planar_rays(log: Log, scans: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """World-plane origins (N, 2), unit directions (N, 2), ranges (N,) and hit flags (N,) of ``scans``' beams."""
    poses = log.poses[scans]
    directions = log.directions[0, 0] if log.directions.shape[0] == 1 else None
    if directions is None:
        raise ParameterError(
            "planar maps need a log whose scans share one beam pattern (directions of shape (1, 1, W, 3))"
        )
    world = np.einsum("sij,wj->swi", poses[:, :2, :2], directions[:, :2].astype(np.float64))
    origin = np.repeat(poses[:, :2, 3][:, None, :], directions.shape[0], axis=1)
    return (
        origin.reshape(-1, 2),
        world.reshape(-1, 2),
        np.nan_to_num(log.ranges[scans, 0].reshape(-1).astype(np.float64)),
        log.hit[scans, 0].reshape(-1),
    )


def count_scans(log: Log, grid: Grid, step: float | None = None, chunk: int = 50) -> ScanCounts:
    """Each scan's hits and pass-throughs on ``grid`` (see the module docstring).

    Args:
        log: a planar log (``H = 1``; e.g. :func:`mi_lidar.io.carmen.read_carmen`).
        grid: the grid.
        step: sampling step of the pass-through traversal, m (default a quarter of a cell).
        chunk: scans processed at once (memory).
    """
    if log.shape[1] != 1:
        raise ParameterError(f"count_scans needs a planar log (H = 1); got H = {log.shape[1]}")
    step = grid.cell / 4 if step is None else step
    hit_start, pass_start, hit_cell, hit_xy, pass_cell = [0], [0], [], [], []
    for first in range(0, log.shape[0], chunk):
        scans = np.arange(first, min(first + chunk, log.shape[0]))
        origin, direction, r, hit = planar_rays(log, scans)
        end = origin + r[:, None] * direction
        end_cell = np.where(hit, grid.cell_of(end), -1)
        length = np.where(hit, np.maximum(r - 0.5 * grid.cell, 0.0), grid.exit_distance(origin, direction))
        ray, cell = ray_cells(grid, origin, direction, length, step)
        keep = cell != end_cell[ray]
        ray, cell = ray[keep], cell[keep]
        beams = log.shape[2]
        scan_of_pass = ray // beams
        for local in range(len(scans)):
            rows = slice(local * beams, (local + 1) * beams)
            mask = hit[rows]
            hit_cell.append(end_cell[rows][mask])
            hit_xy.append(end[rows][mask])
            hit_start.append(hit_start[-1] + int(mask.sum()))
        bounds = np.searchsorted(scan_of_pass, np.arange(len(scans) + 1))
        for local in range(len(scans)):
            pass_cell.append(cell[bounds[local] : bounds[local + 1]])
            pass_start.append(pass_start[-1] + int(bounds[local + 1] - bounds[local]))
    return ScanCounts(
        grid=grid,
        hit_start=np.asarray(hit_start),
        hit_cell=np.concatenate(hit_cell),
        hit_xy=np.concatenate(hit_xy),
        pass_start=np.asarray(pass_start),
        pass_cell=np.concatenate(pass_cell),
    )


class CountMap:
    """Totals of a :class:`ScanCounts` over all scans, with exact leave-out maps."""

    def __init__(self, counts: ScanCounts):
        self.counts = counts
        self.total = counts.moments(np.arange(counts.n_scans))

    def leave_out(self, excluded: np.ndarray) -> dict[str, np.ndarray]:
        """Dense per-cell :data:`MOMENTS` of every scan except ``excluded``."""
        removed = self.counts.moments(excluded)
        out = {k: self.total[k] - removed[k] for k in MOMENTS}
        for k in ("n_hit", "n_pass"):
            out[k] = np.rint(out[k])  # exact integers despite float subtraction
        return out
