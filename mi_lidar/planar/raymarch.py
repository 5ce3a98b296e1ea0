"""The protocol's ray march through leave-out maps: nominal range, incidence, and every cell a beam meets.

For each beam of a query scan (``docs/benchmark_planar.md``): march from the pose in steps of
a quarter cell from 0.02 m to ``reach`` (40 m); the first *occupied* cell of the query's leave-out map
(``occ3``: at least one hit, and hits >= passes / 3) is the nominal hit, its range the exact entry
distance into that cell; a step that crosses a corner (both cell coordinates change) is blocked when
either side cell is occupied (supercover: 8-connected diagonal walls are closed). No occupied cell
within reach, or leaving the grid, is a *nominal miss*. The incidence is the angle between the beam
and the normal of the line fitted (PCA) to the occupied leave-out cells within 15 cm of the hit cell,
accepted when there are at least 4 such cells and the smaller eigenvalue is at most 0.1 times the
larger; otherwise it is unknown.

For pass-through models the march also lists every cell with at least one leave-out hit that the
beam enters, in order (its segments: entry range, hits, passes, occupancy, the incidence on the surface
in it, :meth:`CellLines.surface_incidence`, and that surface's range, :meth:`CellLines.surface_range`), up to
``max_segments`` per beam and ``beyond`` metres past the nominal hit.

The march skips the samples that cannot record anything, and is the same to the bit as the step by step
march. A cell without a whole-log hit has none in any leave-out map (they only subtract), so it is
neither occupied nor a segment, nor does it close a corner; and a ray that stays in its cell learns
nothing new. A ray whose cell is ``R`` cells (Chebyshev) from the nearest cell with a whole-log hit or
the grid's edge (:attr:`~mi_lidar.planar.grid.CountMap.empty_radius`) only meets such cells until it
leaves the square of cells within ``R - 1`` of its cell (its own cell when ``R <= 1``): it jumps to
the last sample before it comes within :data:`SLACK` of that square's edge (far more than rounding
moves a sample), from the cell of that sample, at the distances the step by step march accumulates
(``t += step``), never past its stop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_lidar.planar.grid import CountMap, Grid, LeaveOut, planar_beams
from mi_lidar.planar.trace import PlanarTrace

START = 0.02  # m: the march starts here
SLACK = 1e-3  # cells: a skip ends this far short of a cell edge (rounding moves a sample < 1e-6 cells)
FIT_PAIRS = 32_768  # distinct (query, cell) pairs whose neighbourhoods CellLines.fit takes at once
NEIGHBOURS_REACH = 9  # squared cells: the neighbourhood of a cell is the disc of 3 cells (15 cm at 5 cm cells)
NEIGHBOURS = np.array([(dx, dy) for dx in range(-3, 4) for dy in range(-3, 4) if dx * dx + dy * dy <= NEIGHBOURS_REACH])


def occupied(hits: np.ndarray, passes: np.ndarray) -> np.ndarray:
    """The ``occ3`` rule: at least one hit, and hits >= passes / 3 (a hit in at least 25 % of visits)."""
    return (hits >= 1) & (3 * hits >= passes)


def entry_distance(grid: Grid, origin: np.ndarray, direction: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """Exact distance (m) along unit rays from ``origin`` to where they enter ``cell`` (slab method)."""
    ij = np.stack([cell // grid.shape[1], cell % grid.shape[1]], -1)
    lo = np.asarray(grid.origin) + ij * grid.cell
    hi = lo + grid.cell
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / direction
        t2 = (hi - origin) / direction
    near = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
    return np.max(near, axis=1)


MIN_CELLS = 4  # occupied cells a line fit needs
LINE_RATIO = 0.1  # a line: the smaller spread is at most this share of the larger
ORIENTED_CELLS = 3  # occupied cells with hits an orientation needs
ORIENTED_RATIO = 0.3  # an orientation: the smaller spread of the endpoints is at most this share of the larger


def principal_axis(cxx: np.ndarray, cyy: np.ndarray, cxy: np.ndarray):
    """(larger eigenvalue, smaller eigenvalue, (N, 2) unit normal of the major axis) of 2x2 covariances."""
    half, diff = 0.5 * (cxx + cyy), 0.5 * (cxx - cyy)
    root = np.sqrt(diff * diff + cxy * cxy)
    angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # direction of the line (major axis)
    return half + root, half - root, np.stack([-np.sin(angle), np.cos(angle)], -1)


@dataclass
class CellLines:
    """The local line fits around (query, cell) pairs, fitted once per distinct pair.

    Beams of one scan cross the same cells (at 0.5 deg spacing, several beams per 5 cm cell), so
    each distinct pair is fitted once and every entry reads its pair's fit.

    Attributes:
        at: (E,) the pair of each entry.
        normal, line_like: (U, 2), (U,) the incidence rule's line: PCA of the offsets of the ``occ3``
            occupied leave-out cells within 15 cm, line-like with at least :data:`MIN_CELLS` cells and
            a spread ratio of at most :data:`LINE_RATIO`.
        centre, surface_normal, surface_line: (U, 2), (U, 2), (U,) the surface rule's line: principal
            axis of those cells' leave-out mean endpoints, weighted by their hits, by the same rule.
        oriented: (U,) whether ``surface_normal`` gives the surface's orientation: a looser rule than the line's
            (:data:`ORIENTED_CELLS` cells, spread ratio :data:`ORIENTED_RATIO`), for the incidence at which a
            beam meets any segment (:meth:`surface_incidence`).
        own: (U, 2) the cell's own leave-out mean endpoint (m; NaN for a cell without hits).
        reach: the neighbourhood's radius, m (15 cm at 5 cm cells).
    """

    at: np.ndarray
    normal: np.ndarray
    line_like: np.ndarray
    centre: np.ndarray
    surface_normal: np.ndarray
    surface_line: np.ndarray
    oriented: np.ndarray
    own: np.ndarray
    reach: float

    @classmethod
    def fit(cls, leave: LeaveOut, grid: Grid, query: np.ndarray, cell: np.ndarray) -> CellLines:
        """The fits of (E,) entries (query scan, flat cell) of ``leave``, :data:`FIT_PAIRS` distinct pairs at a time
        (each pair's neighbourhood takes some 30 arrays of 29 x 2 floats at once: 0.85 GB for the 200,000
        pairs of 96 scans of a 360-beam outdoor log)."""
        pairs, at = np.unique(query * grid.size + cell, return_inverse=True)
        parts = [_line_fits(leave, grid, pairs[k : k + FIT_PAIRS]) for k in range(0, max(pairs.size, 1), FIT_PAIRS)]
        normal, line_like, centre, surface_normal, surface_line, oriented = (np.concatenate(v) for v in zip(*parts))
        return cls(
            at=at.reshape(-1),
            normal=normal,
            line_like=line_like,
            centre=centre,
            surface_normal=surface_normal,
            surface_line=surface_line,
            oriented=oriented,
            own=leave.mean_hit(pairs // grid.size, pairs % grid.size),
            reach=float(np.sqrt(NEIGHBOURS_REACH) * grid.cell),
        )

    def incidence(self, direction: np.ndarray) -> np.ndarray:
        """(E,) incidence angle (deg) of unit (E, 2) ``direction`` on each entry's line; NaN where not line-like."""
        return _angle(self.normal[self.at], direction, self.line_like[self.at])

    def surface_incidence(self, direction: np.ndarray) -> np.ndarray:
        """(E,) incidence angle (deg) of unit (E, 2) ``direction`` on each entry's surface; NaN where not oriented.

        The protocol's rule (:meth:`incidence`) knows the incidence on 9 to 23 % of the occupied segments of
        outdoor and cluttered logs (acapulco, FHW): it asks for four cells on a line within one cell's width.
        The endpoints of all scans locate a wall's cells at sub-cell precision, so their principal axis gives
        the surface's orientation from three cells spread at most 0.3 as wide across as along (known on 65
        to 83 %). Chosen on FHW and acapulco by the test NLL of the fitted permeable map (3.895 -> 3.861 and
        4.002 -> 3.986 nats per beam): the protocol's rule loosened alike scored 0.020 and 0.004 worse, spread
        ratios 0.5 and 1 within 0.004 of 0.3.
        """
        return _angle(self.surface_normal[self.at], direction, self.oriented[self.at])

    def surface_range(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """(E,) range (m) along unit rays of the surface in each entry's cell, from the leave-out endpoint hits.

        Where the surface is line-like, the ray crosses the surface rule's line: the endpoints of
        all scans, at sub-cell precision, locate a wall better than the cell's own few hits do, at
        any incidence. The crossing is kept when it lies within 15 cm of the cell's own mean
        endpoint (projected on the ray) and the ray is not parallel to the line (within 84 deg of
        its normal). Elsewhere (corners, clutter, single cells) it is that projection; NaN for a
        cell without leave-out hits.
        """
        own = np.einsum("ek,ek->e", self.own[self.at] - origin, direction)
        normal = self.surface_normal[self.at]
        facing = np.sum(normal * direction, axis=1)
        line_like = self.surface_line[self.at] & (np.abs(facing) > 0.1)
        with np.errstate(divide="ignore", invalid="ignore"):
            crossing = np.sum((self.centre[self.at] - origin) * normal, axis=1) / facing
        return np.where(line_like & (np.abs(crossing - own) <= self.reach), crossing, own)


def _angle(normal: np.ndarray, direction: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(E,) incidence (deg) of unit (E, 2) ``direction`` on lines of unit (E, 2) ``normal``: its angle to the normal,
    0 head-on, 90 grazing; NaN where not ``known``."""
    cos = np.abs(np.sum(normal * direction, axis=1))
    return np.where(known, np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))), np.nan)


def _line_fits(leave: LeaveOut, grid: Grid, pairs: np.ndarray) -> tuple:
    """``(normal, line_like, centre, surface_normal, surface_line, oriented)`` of (U,) distinct
    ``query * size + cell`` ``pairs`` (:class:`CellLines`)."""
    query, cell = pairs // grid.size, pairs % grid.size
    ij = np.stack([cell // grid.shape[1], cell % grid.shape[1]], -1)
    flat = grid.index(ij[:, None, :] + NEIGHBOURS[None])
    valid = flat >= 0
    safe = np.where(valid, flat, 0)
    around = np.broadcast_to(query[:, None], safe.shape)
    hits, passes = leave.counts(around, safe)
    occ = valid & occupied(hits, passes)
    # ---------------- incidence rule: the occupied cells' offsets ---------------------------
    n = occ.sum(axis=1)
    xy = NEIGHBOURS[None].astype(np.float64) * occ[..., None]
    mean = xy.sum(axis=1) / np.maximum(n, 1)[:, None]
    centred = (NEIGHBOURS[None] - mean[:, None, :]) * occ[..., None]
    big, small, normal = principal_axis(
        (centred[..., 0] ** 2).sum(1), (centred[..., 1] ** 2).sum(1), (centred[..., 0] * centred[..., 1]).sum(1)
    )
    line_like = (n >= MIN_CELLS) & (small <= LINE_RATIO * big) & (big > 0)
    # ---------------- surface rule: the occupied cells' mean endpoints, weighted by hits ----
    w = np.where(occ, hits, 0).astype(np.float64)
    endpoints = np.nan_to_num(leave.mean_hit(around, safe))
    centre = (w[..., None] * endpoints).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-12)[:, None]
    dx, dy = (endpoints - centre[:, None, :]).transpose(2, 0, 1)
    big, small, surface_normal = principal_axis((w * dx * dx).sum(1), (w * dy * dy).sum(1), (w * dx * dy).sum(1))
    found = (w > 0).sum(axis=1)
    surface_line = (found >= MIN_CELLS) & (small <= LINE_RATIO * big) & (big > 0)
    oriented = (found >= ORIENTED_CELLS) & (small <= ORIENTED_RATIO * big) & (big > 0)
    return normal, line_like, centre, surface_normal, surface_line, oriented


def march_distances(reach: float, step: float, far: float = np.inf) -> np.ndarray:
    """The march's sample distances (m) up to ``reach``, accumulated as the step by step march adds them.

    They end at the first past ``far`` (where every ray has left the grid), so an unbounded ``reach`` ends too.
    """
    t, out = START, []
    while t <= reach:
        out.append(t)
        if t > far:
            break
        t += step
    return np.array(out)


def _counts(leave: LeaveOut, query: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`LeaveOut.counts`, looked up only in cells with a whole-log hit: (0, 0) elsewhere."""
    hits, passes = np.zeros(cell.shape, np.int64), np.zeros(cell.shape, np.int64)
    some = np.flatnonzero(leave.totals.hits[cell] > 0)
    hits[some], passes[some] = leave.counts(query[some], cell[some])
    return hits, passes


def box_exit(grid: Grid, origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Distance (m) along unit rays to where they come within :data:`SLACK` cells of the edge of cells ``[lo, hi)``.

    ``lo``, ``hi``: (N, 2) cell coordinates of the boxes' corners (``hi`` exclusive). Before that
    distance, a ray's samples lie in the box (with :data:`SLACK` to spare for rounding).
    """
    lo_xy = np.asarray(grid.origin) + (lo + SLACK) * grid.cell
    hi_xy = np.asarray(grid.origin) + (hi - SLACK) * grid.cell
    with np.errstate(divide="ignore", invalid="ignore"):
        far = np.where(direction > 0, hi_xy - origin, lo_xy - origin) / direction
    return np.min(np.where(direction == 0, np.inf, far), axis=1)


def trace_scans(
    log,
    grid: Grid,
    cmap: CountMap,
    scans: np.ndarray,
    excluded: list[np.ndarray],
    reach: float = 40.0,
    max_segments: int = 8,
    beyond: float = 10.0,
) -> PlanarTrace:
    """March every beam of ``scans`` through its scan's leave-out map (see the module docstring).

    Args:
        log: the planar log.
        grid, cmap: the grid and the whole-log counts.
        scans: (Q,) query scans.
        excluded: per query, the scans its map leaves out.
        reach: march limit, m.
        max_segments: segments kept per beam.
        beyond: metres past the nominal hit the segments are collected.
    """
    leave = cmap.leave_out(excluded)
    origin, direction, z = planar_beams(log, scans)
    q_count, n_beams = z.shape
    o, d = origin.reshape(-1, 2), direction.reshape(-1, 2)
    query = np.repeat(np.arange(q_count), n_beams)
    b = o.shape[0]
    step = grid.cell / 4
    corners = np.asarray(grid.origin) + np.array([[0, 0], [0, 1], [1, 0], [1, 1]]) * np.asarray(grid.shape) * grid.cell
    with np.errstate(divide="ignore"):  # every ray is out of the grid past ``far``
        far = np.max(np.hypot(*(corners[None] - o[:, None]).T).max(axis=0) / np.hypot(*d.T), initial=0.0) + grid.cell
    distances = march_distances(reach, step, far)
    radius = cmap.empty_radius
    nominal = np.full(b, np.nan)
    first_cell = np.full(b, -1, np.int64)
    seg_cell = np.full((b, max_segments), -1, np.int64)
    seg_count = np.zeros(b, np.int64)
    stop_at = np.full(b, reach)
    at = np.zeros(b, np.int64)  # each ray's sample: it is at distances[at]
    alive = np.arange(b) if distances.size else np.zeros(0, np.int64)
    prev_ij = grid.ij(o + START * d)
    # a ray looks at its cell even if it stays in it on the first step, and after a blocked corner
    pending = np.ones(b, bool)
    while alive.size:
        t = distances[at[alive]]
        ij_all = grid.ij(o[alive] + t[:, None] * d[alive])
        moved = np.any(ij_all != prev_ij[alive], axis=1) | pending[alive]
        # a ray that stays in its cell learns nothing new (same cell, same counts): only the moved ones look
        act, ij = alive[moved], ij_all[moved]
        flat = grid.index(ij)
        outside = flat < 0
        cand = np.where(outside, 0, flat)
        diagonal = np.all(ij != prev_ij[act], axis=1) & ~outside
        # ---------------- the cell of this step, and the side cells of a corner crossing ----------
        blocked_cell = np.full(act.size, -1, np.int64)
        if np.any(diagonal):
            rows = np.flatnonzero(diagonal)
            p = prev_ij[act][rows]
            for side in (np.stack([ij[rows, 0], p[:, 1]], -1), np.stack([p[:, 0], ij[rows, 1]], -1)):
                side_flat = grid.index(side)
                ok = side_flat >= 0
                h, n = _counts(leave, query[act][rows], np.where(ok, side_flat, 0))
                occ = ok & occupied(h, n)
                take = occ & (blocked_cell[rows] < 0)
                blocked_cell[rows[take]] = side_flat[take]
        h, n = _counts(leave, query[act], cand)
        with_hits = ~outside & (h >= 1)
        occ_here = with_hits & occupied(h, n)
        hit_cell = np.where(blocked_cell >= 0, blocked_cell, np.where(occ_here, cand, -1))
        # ---------------- segments: cells with leave-out hits, in order, once each ------------------
        new = np.where(blocked_cell >= 0, blocked_cell, np.where(with_hits, cand, -1))
        count = seg_count[act]
        last = np.where(count > 0, seg_cell[act, np.maximum(count - 1, 0)], -1)
        first = (hit_cell >= 0) & (first_cell[act] < 0)
        # a full list still takes the nominal hit, in its last slot
        record = (new >= 0) & (new != last) & ((count < max_segments) | first)
        rows = act[record]
        slot = np.minimum(seg_count[rows], max_segments - 1)
        seg_cell[rows, slot] = new[record]
        seg_count[rows] = slot + 1
        # ---------------- the nominal hit: the first occupied cell ------------------------------
        rows = act[first]
        first_cell[rows] = hit_cell[first]
        stop_at[rows] = np.minimum(reach, t[moved][first] + beyond)
        prev_ij[act] = ij
        pending[act] = blocked_cell >= 0
        full = (seg_count[act] >= max_segments) & (first_cell[act] >= 0)
        done = np.zeros(alive.size, bool)
        done[moved] = outside | full
        done |= t + step > stop_at[alive]
        alive, ij_all = alive[~done], ij_all[~done]
        # ---------------- the next sample, past the samples that would record nothing --------------
        # Until it leaves the cells within R - 1 of its cell of empty radius R (at least its own cell), a ray
        # samples cells without hits, crossing corners between them, or its own cell again: nothing to
        # record. It skips those samples, up to the last one before its stop, and goes on from the last
        # skipped sample's cell (a pending ray looks at its cell again first).
        flat = grid.index(ij_all)
        go = ~pending[alive] & (flat >= 0)
        rows, ij = alive[go], ij_all[go]
        half = np.maximum(radius[flat[go]].astype(np.int64) - 1, 0)[:, None]
        leaves = box_exit(grid, o[rows], d[rows], ij - half, ij + half + 1)
        end = np.searchsorted(distances, stop_at[rows], side="right") - 1  # the last sample within the stop
        to = np.minimum(np.searchsorted(distances, leaves) - 1, end - 1)
        ahead = to > at[rows]
        rows, to = rows[ahead], to[ahead]
        at[rows] = to
        prev_ij[rows] = grid.ij(o[rows] + distances[to][:, None] * d[rows])
        at[alive] += 1
    has = first_cell >= 0
    nominal[has] = entry_distance(grid, o[has], d[has], first_cell[has])
    # ---------------- segment arrays (CSR) ------------------------------------------------------
    rows = np.repeat(np.arange(b), seg_count)
    cells = seg_cell[np.arange(max_segments)[None, :] < seg_count[:, None]]  # row-major: each beam's in order
    hits, passes = leave.counts(query[rows], cells)
    seg_range = entry_distance(grid, o[rows], d[rows], cells)
    lines = CellLines.fit(leave, grid, query[rows], cells)
    seg_inc = lines.incidence(d[rows])
    surface = lines.surface_range(o[rows], d[rows])
    # the nominal cell is one of its beam's segments (a full list still records it): its incidence is that segment's
    seg_start = np.concatenate([[0], np.cumsum(seg_count)])
    incidence = np.full(b, np.nan)
    incidence[has] = seg_inc[seg_start[:-1][has] + np.argmax(seg_cell[has] == first_cell[has, None], axis=1)]
    return PlanarTrace(
        scan=np.repeat(np.asarray(scans), n_beams),
        beam=np.tile(np.arange(n_beams), q_count),
        z=z.ravel(),
        nominal=nominal,
        incidence=incidence,
        seg_start=seg_start,
        seg_range=seg_range,
        seg_hits=hits,
        seg_passes=passes,
        seg_occupied=occupied(hits, passes),
        seg_incidence=lines.surface_incidence(d[rows]),
        seg_line_incidence=seg_inc,
        seg_surface=surface,
    )
