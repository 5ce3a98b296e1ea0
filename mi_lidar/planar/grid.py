"""Count maps of planar logs on a regular 2D grid, with exact leave-out maps per query scan.

Following the real-planar protocol (``docs/benchmark_planar.md``): every scan contributes
to the cells it touches. A return closer than ``reach`` (40 m) adds an endpoint *hit* to its cell;
every return adds a *pass-through* to each cell its beam crosses from the sensor to one cell short of
the return (sampled every quarter cell); beams without a return clear nothing. Contributions are
additive, so the map of a query scan that leaves some scans out is the total minus their
contributions: :class:`CountMap` keeps the totals and, per query scan, the sparse corrections of its
excluded scans. Pass-throughs and corrections are kept only for cells that hold a hit somewhere in the
log, the only cells that can be occupied.
The endpoints' coordinates are summed the same way, so every cell also has the exact leave-out mean
of its endpoint hits (where inside the cell the surface is).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from mi_lidar.core.errors import LogFormatError, ParameterError
from mi_lidar.core.log import Log

REACH = 40.0  # m: returns beyond this add no endpoint hit (the protocol's march limit)
EMPTY_CAP = 64  # cells: empty radii are counted up to this (3.2 m at 5 cm cells)
STILL_SPREAD = 0.25  # m: median spread of a beam's returns between scans above which a log at one pose moved


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
        if not cell > 0:
            raise ParameterError(f"grid: cell={cell} m must be > 0, e.g. 0.05")
        lo = points.min(axis=0) - margin
        hi = points.max(axis=0) + margin
        return cls(
            origin=(float(lo[0]), float(lo[1])),
            cell=float(cell),
            shape=tuple(int(v) for v in np.ceil((hi - lo) / cell)),
        )

    @property
    def size(self) -> int:
        """Number of cells."""
        return self.shape[0] * self.shape[1]

    def ij(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) integer cell coordinates of world points (m)."""
        return np.floor((xy - np.asarray(self.origin)) / self.cell).astype(np.int64)

    def index(self, ij: np.ndarray) -> np.ndarray:
        """Flat indices of (..., 2) integer cell coordinates; -1 outside the grid."""
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < self.shape[0]) & (ij[..., 1] >= 0) & (ij[..., 1] < self.shape[1])
        return np.where(inside, ij[..., 0] * self.shape[1] + ij[..., 1], -1)

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """Flat cell index of (..., 2) world points (m); -1 outside the grid."""
        return self.index(self.ij(xy))

    def center(self, flat: np.ndarray) -> np.ndarray:
        """(N, 2) world centres (m) of flat cell indices."""
        ij = np.stack([flat // self.shape[1], flat % self.shape[1]], axis=-1)
        return np.asarray(self.origin) + (ij + 0.5) * self.cell


def check_planar_shape(log: Log) -> None:
    """Refuse a log that is not (S, N, 1): N beams by one firing, all scans sharing one beam pattern."""
    if log.shape[2] != 1 or log.directions.shape[0] != 1:
        raise ParameterError(
            f"planar maps need a planar log of N beams x 1 firing sharing one pattern (directions (1, N, 1, 3)); "
            f"got shape {log.shape} with directions {log.directions.shape}; read CARMEN logs with "
            "mi_lidar.io.carmen.read_carmen"
        )


def check_moved(log: Log, source) -> None:
    """Refuse a planar log whose scans all share one pose while the same beam's returns differ between them by more
    than :data:`STILL_SPREAD` (a scanner that moved, logged without its poses): any map of it is a smear of every
    scan. A scanner that stood still is kept.

    Raises:
        LogFormatError: such a log (``source``, its file, named first).
    """
    if log.shape[0] < 2 or not np.all(log.poses == log.poses[0]):
        return
    z = np.where(log.hit[:, :, 0], log.ranges[:, :, 0], np.nan)
    seen = np.isfinite(z).sum(axis=0) >= 2
    if not seen.any():
        return
    z = z[:, seen]
    spread = float(np.median(np.nanmedian(np.abs(z - np.nanmedian(z, axis=0)), axis=0)))
    if spread > STILL_SPREAD:
        which = "the identity" if np.allclose(log.poses[0], np.eye(4)) else "one pose"
        raise LogFormatError(
            f"{source}: all {log.shape[0]:,} scans have the same pose ({which}), yet a beam's returns differ between "
            f"scans by a median {spread:.2f} m: the scanner moved and the log has no poses, so the map would be a "
            "smear of every scan. Give a log with SLAM-corrected poses (CARMEN FLASER lines, or the .gfs.log a "
            f"SLAM such as GMapping writes); a scanner that stood still gives under {STILL_SPREAD:g} m and is mapped"
        )


def planar_beams(log: Log, scans: np.ndarray | None = None):
    """World-plane origins (S, N, 2), unit directions (S, N, 2), readings (S, N; NaN = miss) of a planar log.

    The log is (S, N, 1): N beams by one firing, all scans sharing one beam pattern (:func:`check_planar_shape`).
    """
    check_planar_shape(log)
    scans = np.arange(log.shape[0]) if scans is None else np.asarray(scans)
    poses = log.poses[scans]
    local = log.directions[0, :, 0, :2].astype(np.float64)
    world = np.einsum("sij,nj->sni", poses[:, :2, :2], local)
    origin = np.repeat(poses[:, None, :2, 3], local.shape[0], axis=1)
    z = np.where(log.hit[scans, :, 0], log.ranges[scans, :, 0], np.nan).astype(np.float64)
    return origin, world, z


def march_cells(
    grid: Grid, origin: np.ndarray, direction: np.ndarray, length: np.ndarray, step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Cells each ray crosses on ``[0, length)``, sampled every ``step`` m: unique (ray, cell) pairs.

    Rays come in order, each ray's cells in the order it crosses them. A straight ray never enters a
    cell again once it has left it (the sampled coordinates are monotone along it), so its samples'
    cells repeat only in runs, and dropping the repeats of a run leaves every cell once.
    """
    count = np.maximum(np.ceil(length / step).astype(np.int64), 0)
    ray = np.repeat(np.arange(len(count)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    t = (np.arange(ray.size) - first) * step
    flat = grid.cell_of(origin[ray] + t[:, None] * direction[ray])
    keep = flat >= 0
    ray, flat = ray[keep], flat[keep]
    new = np.ones(ray.size, bool)
    new[1:] = (flat[1:] != flat[:-1]) | (ray[1:] != ray[:-1])
    return ray[new], flat[new]


@dataclass
class ScanCounts:
    """Per-scan contributions to the map (CSR over scans).

    Attributes:
        grid: the grid.
        hit_start, hit_cell: offsets (S + 1,) and int32 cells of each scan's endpoint hits.
        hit_xy: (H, 2) world position (m) of each endpoint hit.
        pass_start, pass_cell: offsets (S + 1,) and int32 cells of each scan's pass-throughs (one per beam
            and cell), in cells with an endpoint hit in the whole log only (:func:`count_scans`).
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

    def cells(self, scans: np.ndarray, kind: str) -> np.ndarray:
        """All contributed cells (with repeats) of ``scans`` of ``kind`` (``"hit"`` or ``"pass"``)."""
        start, cell = (self.hit_start, self.hit_cell) if kind == "hit" else (self.pass_start, self.pass_cell)
        parts = [cell[start[s] : start[s + 1]] for s in np.asarray(scans, np.int64)]
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)

    def hit_points(self, scans: np.ndarray) -> np.ndarray:
        """(H, 2) endpoint positions of ``scans``' hits, in the order of :meth:`cells` ``(scans, "hit")``."""
        parts = [self.hit_xy[self.hit_start[s] : self.hit_start[s + 1]] for s in np.asarray(scans, np.int64)]
        return np.concatenate(parts) if parts else np.zeros((0, 2))


SAMPLES_PER_CHUNK = 5_000_000  # beam samples a counting thread marches at once (about 100 bytes each at its peak)


def scans_per_chunk(log: Log, cell: float) -> int:
    """How many scans of ``log`` hold :data:`SAMPLES_PER_CHUNK` beam samples (every quarter of ``cell`` m from
    the sensor to each return) on average: 1 to 64."""
    marched = np.nansum(np.where(log.hit, log.ranges, 0.0)) / max(log.shape[0], 1) / (cell / 4)  # per scan
    return int(np.clip(SAMPLES_PER_CHUNK / max(marched, 1.0), 1, 64))


def count_scans(
    log: Log, grid: Grid, reach: float = REACH, chunk: int | None = None, progress=None, workers: int = 1
) -> ScanCounts:
    """Each scan's endpoint hits and pass-throughs on ``grid`` (see the module docstring).

    Pass-throughs are kept only in cells with an endpoint hit in the whole log, the only cells that can
    be occupied (``occ3`` needs a hit): the free space every beam crosses is most of the passes and
    none of the map, so the per-scan lists stay a fraction of the log's march. The endpoints are found
    first, then chunks of ``chunk`` scans are marched on ``workers`` threads (numpy releases the GIL
    in its loops); by default :func:`scans_per_chunk`, so that the march's memory does not grow with the
    sensor's range (64 scans of a 360-beam outdoor log returning at up to 82 m held 4.8 GB at once).
    Cells are int32 (a grid holds fewer than 2**31 cells).
    """
    chunk = scans_per_chunk(log, grid.cell) if chunk is None else chunk
    chunks = [np.arange(first, min(first + chunk, log.shape[0])) for first in range(0, log.shape[0], chunk)]
    ends, points = zip(*(_endpoints(log, grid, reach, scans) for scans in chunks))
    hit_cells = [e[e >= 0] for end in ends for e in end]
    hit_points = [p[e >= 0] for end, point in zip(ends, points) for e, p in zip(end, point)]
    hit_cell = np.concatenate(hit_cells)
    can_hold = np.zeros(grid.size, bool)
    can_hold[hit_cell] = True
    pass_cells = []
    marched = in_threads(lambda k: _passes(log, grid, can_hold, chunks[k], ends[k]), range(len(chunks)), workers)
    for scans, passes in zip(chunks, marched):
        pass_cells += passes
        if progress is not None:
            progress(scans[-1] + 1, log.shape[0])
    return ScanCounts(
        grid,
        np.concatenate([[0], np.cumsum([c.size for c in hit_cells])]),
        hit_cell,
        np.concatenate(hit_points),
        np.concatenate([[0], np.cumsum([c.size for c in pass_cells])]),
        np.concatenate(pass_cells),
    )


def _endpoints(log: Log, grid: Grid, reach: float, scans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S, N) int32 endpoint-hit cell of every beam of ``scans`` (-1: no return closer than ``reach``), and
    (S, N, 2) return positions (m)."""
    origin, direction, z = planar_beams(log, scans)
    point = origin + np.nan_to_num(z)[..., None] * direction
    return np.where(np.isfinite(z) & (z < reach), grid.cell_of(point), -1).astype(np.int32), point


def _passes(log: Log, grid: Grid, can_hold: np.ndarray, scans: np.ndarray, end: np.ndarray) -> list:
    """Per scan of ``scans``: the int32 cells its returns pass through (one per beam and cell), where ``can_hold``,
    short of each beam's endpoint cell ``end`` (S, N) (:func:`_endpoints`)."""
    origin, direction, z = planar_beams(log, scans)
    n_beams = origin.shape[1]
    o, d, r = origin.reshape(-1, 2), direction.reshape(-1, 2), z.ravel()
    hit = np.isfinite(r)
    ray, cell = march_cells(grid, o, d, np.where(hit, np.nan_to_num(r) - grid.cell, 0.0), grid.cell / 4)
    keep = can_hold[cell]
    ray, cell = ray[keep], cell[keep]
    keep = cell != end.ravel()[ray]  # a beam's own endpoint hit is not a pass
    ray, cell = ray[keep], cell[keep].astype(np.int32)
    bounds = np.searchsorted(ray // n_beams, np.arange(len(scans) + 1))
    return [cell[bounds[k] : bounds[k + 1]] for k in range(len(scans))]


def in_threads(work, items: list, workers: int):
    """``work(item)`` for every item, on ``workers`` threads, yielded in order (numpy work releases the GIL)."""
    if workers <= 1 or len(items) <= 1:
        yield from map(work, items)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(workers, len(items))) as pool:
        yield from pool.map(work, items)


class CountMap:
    """Whole-log hit and pass-through totals, and the exact leave-out corrections of query scans.

    Args:
        counts: the per-scan contributions.
    """

    def __init__(self, counts: ScanCounts):
        self.counts = counts
        size = counts.grid.size
        self.hits = np.bincount(counts.hit_cell, minlength=size).astype(np.int32)
        self.passes = np.bincount(counts.pass_cell, minlength=size).astype(np.int32)
        self.hit_sum = np.stack(
            [np.bincount(counts.hit_cell, weights=counts.hit_xy[:, k], minlength=size) for k in range(2)], axis=1
        )

    @functools.cached_property
    def empty_radius(self) -> np.ndarray:
        """(size,) uint8 per cell: Chebyshev distance (cells, at most :data:`EMPTY_CAP`) to the nearest whole-log hit.

        Outside the grid counts as hits, so every cell within ``radius - 1`` cells of a cell is in the grid
        and has no hit in any leave-out map (the ray march skips such cells, :mod:`mi_lidar.planar.raymarch`).
        """
        free = np.pad((self.hits == 0).reshape(self.counts.grid.shape), 1)  # a border of hits
        distance = ndimage.distance_transform_cdt(free, metric="chessboard")[1:-1, 1:-1]
        return np.minimum(distance, EMPTY_CAP).astype(np.uint8).ravel()

    def leave_out(self, excluded: list[np.ndarray]) -> LeaveOut:
        """The sparse corrections of a batch of query scans; ``excluded[q]`` are the scans query ``q`` leaves out.

        Only cells with a hit in the whole log are kept (no other cell can be occupied).
        """
        size = self.counts.grid.size
        parts: dict[str, tuple[list, list]] = {"hit": ([], []), "pass": ([], [])}
        sums = []
        for q, scans in enumerate(excluded):
            for kind, (keys, counts) in parts.items():
                cells = self.counts.cells(scans, kind)
                kept = self.hits[cells] > 0
                unique, inverse, n = np.unique(cells[kept].astype(np.int64), return_inverse=True, return_counts=True)
                keys.append(q * size + unique)
                counts.append(n)
                if kind == "hit":
                    xy = self.counts.hit_points(scans)[kept]
                    sums.append(
                        np.stack([np.bincount(inverse, weights=xy[:, k], minlength=unique.size) for k in range(2)], 1)
                    )
        hit_keys, hit_n = (np.concatenate(v) for v in parts["hit"])
        pass_keys, pass_n = (np.concatenate(v) for v in parts["pass"])
        keys = np.union1d(hit_keys, pass_keys)
        dh, dp = np.zeros(keys.size, np.int32), np.zeros(keys.size, np.int32)
        ds = np.zeros((keys.size, 2))
        at = np.searchsorted(keys, hit_keys)
        dh[at] = hit_n
        ds[at] = np.concatenate(sums) if sums else np.zeros((0, 2))
        dp[np.searchsorted(keys, pass_keys)] = pass_n
        return LeaveOut(self, keys, dh, dp, ds)


@dataclass
class LeaveOut:
    """Leave-out counts of a batch of query scans (see :meth:`CountMap.leave_out`).

    Attributes:
        totals: the whole-log map.
        keys: sorted ``q * size + cell`` of the corrected cells.
        dh, dp: hits and pass-throughs the query's excluded scans put in those cells.
        ds: (K, 2) sum of the positions (m) of those hits.
    """

    totals: CountMap
    keys: np.ndarray
    dh: np.ndarray
    dp: np.ndarray
    ds: np.ndarray

    def _found(self, query: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index into the corrections of each (query, cell), and whether it has one."""
        if not self.keys.size:
            return np.zeros(np.shape(cell), np.int64), np.zeros(np.shape(cell), bool)
        key = query * self.totals.counts.grid.size + cell
        i = np.minimum(np.searchsorted(self.keys, key), self.keys.size - 1)
        return i, self.keys[i] == key

    @staticmethod
    def _taken(values: np.ndarray, i: np.ndarray, found: np.ndarray) -> np.ndarray:
        """``values[i]`` where ``found``, else 0 (``values`` may be empty: a batch whose excluded scans hit nothing)."""
        out = np.zeros(found.shape + values.shape[1:], values.dtype)
        out[found] = values[i[found]]
        return out

    def mean_hit(self, query: np.ndarray, cell: np.ndarray) -> np.ndarray:
        """(..., 2) leave-out mean position (m) of the endpoint hits in ``cell`` (NaN where it has none)."""
        i, found = self._found(query, cell)
        hits = self.totals.hits[cell] - self._taken(self.dh, i, found)
        total = self.totals.hit_sum[cell] - self._taken(self.ds, i, found)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(hits[..., None] > 0, total / hits[..., None], np.nan)

    def counts(self, query: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(hits, pass-throughs) of ``cell`` in the leave-out map of query ``query`` (arrays of equal shape)."""
        i, found = self._found(query, cell)
        hits = self.totals.hits[cell].astype(np.int64) - self._taken(self.dh, i, found)
        passes = self.totals.passes[cell].astype(np.int64) - self._taken(self.dp, i, found)
        return hits, passes
