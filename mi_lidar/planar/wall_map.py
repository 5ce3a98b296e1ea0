"""The permeable wall map of a planar log: where its surfaces lie and how often they stop a beam.

A planar scanner (a SICK LMS: every beam in one horizontal plane) sees a 2D world, so its map is a map of that
plane, counted from the log itself on a grid of ``cell`` m as the real-planar protocol counts
(:func:`mi_lidar.planar.grid.count_scans`, ``docs/benchmark_planar.md``): every return adds a *hit* to the cell it
ends in and a *pass-through* to every cell its beam crosses up to one cell short of that; a no-return clears
nothing (a dark or glancing surface is silent too, not only free space). Unlike the benchmark's maps, every return
counts, however far, and the grid spans them all. An element stops a beam that reaches it with

    p = (hits + a) / (hits + passes + a + b),   Beta prior (a, b) = :data:`PRIOR` = (1, 0.1):

the counting estimate, pulled towards a wall for elements seen rarely: hit once and never passed 0.95, a wall hit
20 times and never passed 0.995, hit once and passed 20 times (a person's legs) 0.09. (A symmetric prior,
Beta(0.5, 0.5), lets 2-5 % of the beams through walls seen 10-20 times; on the Intel log, scored on itself by
``compare`` with cell boxes, it explained some no-returns by such leaks, NLL 3.32 against 3.37 nats/ray, but
sampled returns from behind the walls: histogram L1 0.093 against 0.062 m.)

Every cell with a hit holds one element, vertical from :data:`HALF_HEIGHT` below to :data:`HALF_HEIGHT` above the
scan plane (the poses' median height; a planar beam never meets a top or bottom, and +-0.5 m tolerates a scanner
that tilts by a degree out to 28 m):

- **a surface where the hits lie on a line**: the hits within 15 cm (the cell's :data:`NEIGHBOURS`, at least
  :data:`MIN_CELLS` cells) spread along one direction, the smaller principal variance at most :data:`LINE_RATIO`
  times the larger (the benchmark's line rule, :mod:`mi_lidar.planar.raymarch`, on the hits themselves). The
  surface is that direction's line through the mean of the cell's own hits, clipped to the cell: one quad, which a
  beam crosses once, so it stops a beam with ``p``. Where the lines of two neighbouring cells cross their common
  edge, both end at the mean of the two crossings, so a wall's quads join without gaps. A beam stops at the mean
  of the hits rather than at the cell's edge, which lies on average half a cell in front of the surface (on the
  Intel log a returning beam ended 2.3 cm behind its cell's entry edge). Its counts are the log's beams traced
  through the surfaces (:func:`count_crossings`): a returning beam hits the surface it crosses nearest to its
  return (within :data:`WINDOW` cells; else the one in its end cell) and passes the surfaces it crossed before;
  the cells' own counts would let the beams that ran past a thin surface inside its cell (grazing a wall, or
  ending in the cell just behind it) count as passes of it.
- **a box elsewhere** (corners, clutter, cells hit from many sides): the cell's four side faces, counted as the
  grid counts. A beam crosses two faces of a box, so each face stops it with ``q = 1 - sqrt(1 - p)``
  (:func:`face_p_hit`): ``1 - (1 - q)^2 = p``. Neighbouring boxes share a face; it is written once, with
  ``1 - (1 - q_1)(1 - q_2)``, so a beam that crosses both boxes passes with the same ``(1 - q_1)^2 (1 - q_2)^2``
  and no two triangles coincide (Embree would report coincident triangles in either order).

On the Intel log (5 cm cells) 41 % of the cells with a hit, holding 55 % of the hits, are surfaces (a surface no
beam stopped at, its cell's hits all nearest to its neighbours' surfaces, is left out: 74 of them). Scored on the
log itself by ``compare``, the map gives NLL 3.218 nats/ray against 3.371 with a box in every cell, median |range
error| 0.037 against 0.045 m, p90 0.275 against 0.308 m, histogram L1 0.062 m and F1 0.986 both; a simulated scan
stops a median 0.9 cm in front of the log's returns, against 2.0 cm. Grazing beams (75-90 deg of incidence) score
worse, 5.33 against 4.43 nats/ray: the boxes' faces across a wall stopped them early, and a centimetre across a
wall is six along a beam at 80 deg. Measured the same way: quads in every cell (a non-line cell's quad facing its
beams) let the beams through cells hit from several sides (histogram L1 0.107 m); surfaces with their cells' counts
let them through the walls (0.081 m); a line rule of 0.2 (75 % of the hits in surfaces) scores NLL 3.184 with
histogram L1 0.070 m; a window of 1 or 3 cells NLL 3.208 and 3.226, histogram L1 0.064 and 0.061 m.

Example::

    walls = count_walls(read_any("intel-corrected.log.gz"))
    vertices, triangles, p_face = wall_faces(walls)
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.log import Log
from mi_lidar.planar.beams import permeability
from mi_lidar.planar.grid import Grid, count_scans, in_threads, march_cells, planar_beams, scans_per_chunk
from mi_lidar.planar.protocol import map_grid
from mi_lidar.planar.raymarch import LINE_RATIO, MIN_CELLS, NEIGHBOURS, principal_axis

CELL = 0.05  # m: map cell (the protocol's)
HALF_HEIGHT = 0.5  # m: the elements reach this far below and above the scan plane
PRIOR = (1.0, 0.1)  # Beta prior (a, b) of a hit probability: a surface seen once is a wall
WINDOW = 2  # cells: a beam hits the surface it crosses nearest its return, if that lies this close


@dataclass
class WallMap:
    """The elements of a planar log's wall map: one per cell with a hit, a surface or a box.

    Attributes:
        grid: the map grid.
        cells: (C,) flat indices of the cells with an element, ascending.
        hits, passes: (C,) hits and pass-throughs of each element: a box's are its cell's, a surface's are
            the beams that stopped at it and passed it (:func:`count_crossings`).
        plane_z: height of the scan plane (m): the poses' median height.
        surface: (C,) True where the element is a surface, False for a box.
        ends: (C, 2, 2) a surface's two ends (m, world xy); NaN for a box.
    """

    grid: Grid
    cells: np.ndarray
    hits: np.ndarray
    passes: np.ndarray
    plane_z: float
    surface: np.ndarray
    ends: np.ndarray

    @property
    def p_hit(self) -> np.ndarray:
        """(C,) probability that the element stops a beam that reaches it, under the Beta :data:`PRIOR`."""
        return permeability(self.hits, self.passes, *PRIOR)


def face_p_hit(p: np.ndarray) -> np.ndarray:
    """The hit probability ``q = 1 - sqrt(1 - p)`` of each of two faces that together stop a beam with ``p``."""
    return 1.0 - np.sqrt(1.0 - np.asarray(p, np.float64))


def count_walls(log: Log, cell: float = CELL, progress=None) -> WallMap:
    """The wall map of ``log``: its cells' counts, their surfaces, and the surfaces' counts (module docstring).

    Args:
        log: a planar log (S scans x N beams x 1 firing, world poses).
        cell: grid cell, m.
        progress: ``progress(stage, fraction)``, or None.
    """
    if not 0.005 <= cell <= 1.0:
        raise ParameterError(f"cell={cell} m must lie in [0.005, 1], e.g. {CELL}")
    report = progress or (lambda stage, fraction: None)
    grid = map_grid(log, cell, reach=np.inf, trim=0.0)
    chunk = scans_per_chunk(log, cell)
    workers = os.cpu_count() or 1
    counts = count_scans(
        log,
        grid,
        reach=np.inf,
        chunk=chunk,
        workers=workers,
        progress=lambda done, total: report("counting hits and passes", done / total),
    )
    cells, at, hits = np.unique(counts.hit_cell.astype(np.int64), return_inverse=True, return_counts=True)
    passes = np.bincount(np.searchsorted(cells, counts.pass_cell), minlength=cells.size)  # passes: only hit cells
    offset, spread = _hit_moments(grid, cells, at, counts.hit_xy)
    surface, normal = surface_lines(grid, cells, hits, offset, spread)
    ends = np.full((cells.size, 2, 2), np.nan)
    ends[surface] = surface_ends(grid, cells[surface], offset[surface], normal[surface])
    hits[surface], passes[surface] = count_crossings(
        log,
        grid,
        cells[surface],
        ends[surface],
        chunk,
        workers,
        progress=lambda done, total: report("tracing the beams through the surfaces", done / total),
    )
    keep = hits > 0  # a surface no beam stopped at: the hits in its cell stopped at its neighbours
    return WallMap(
        grid, cells[keep], hits[keep], passes[keep], float(np.median(log.poses[:, 2, 3])), surface[keep], ends[keep]
    )


def _hit_moments(grid: Grid, cells: np.ndarray, at: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C, 2) mean (m, from the cell's lower corner) and (C, 3) covariance ``xx, yy, xy`` (m^2) of the hits ``xy``
    (H, 2; m, world) that lie in ``cells[at]``."""
    n = np.bincount(at, minlength=cells.size)[:, None]
    corner = np.asarray(grid.origin) + np.stack([cells // grid.shape[1], cells % grid.shape[1]], 1) * grid.cell
    local = xy - corner[at]
    mean = np.stack([np.bincount(at, local[:, k], cells.size) for k in range(2)], 1) / n
    d = local - mean[at]
    products = (d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1])
    return mean, np.stack([np.bincount(at, w, cells.size) for w in products], 1) / n


def surface_lines(
    grid: Grid, cells: np.ndarray, hits: np.ndarray, offset: np.ndarray, spread: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where the hits around each cell lie on a line, and the line's unit normal (module docstring).

    Args:
        grid: the map grid.
        cells: (C,) flat indices of the cells with a hit, ascending.
        hits: (C,) their hits.
        offset: (C, 2) mean of each cell's hits from its lower corner, m.
        spread: (C, 3) covariance ``xx, yy, xy`` of each cell's hits, m^2.

    Returns:
        (C,) whether the hits within :data:`NEIGHBOURS` lie on a line, and (C, 2) the line's unit normal.
    """
    nx, ny = grid.shape
    i, j = cells // ny, cells % ny
    found = np.zeros(cells.size)
    moments = np.zeros((cells.size, 6))  # sums over the hits of 1, x, y, xx, yy, xy (m from the cell's corner)
    for dx, dy in NEIGHBOURS:
        flat = (i + dx) * ny + (j + dy)
        k = _index_in(cells, flat)
        there = (k >= 0) & (i + dx >= 0) & (i + dx < nx) & (j + dy >= 0) & (j + dy < ny)
        k = np.maximum(k, 0)
        x, y = dx * grid.cell + offset[k, 0], dy * grid.cell + offset[k, 1]
        sxx, syy, sxy = spread[k].T
        moments += np.where(there, hits[k], 0)[:, None] * np.stack(
            [np.ones_like(x), x, y, x * x + sxx, y * y + syy, x * y + sxy], 1
        )
        found += there
    w = moments[:, 0]
    mx, my = moments[:, 1] / w, moments[:, 2] / w
    big, small, normal = principal_axis(
        moments[:, 3] / w - mx * mx, moments[:, 4] / w - my * my, moments[:, 5] / w - mx * my
    )
    return (found >= MIN_CELLS) & (small <= LINE_RATIO * big) & (big > 0), normal


def _edge_keys(grid: Grid):
    """Keys of the grid's cell edges: ``vertical(I, j)`` is the edge x = I along row j, ``horizontal(i, J)`` the
    edge y = J along column i; every edge has one key."""
    nx, ny = grid.shape
    vertical = lambda line, row: line * ny + row  # noqa: E731
    horizontal = lambda col, line: (nx + 1) * ny + col * (ny + 1) + line  # noqa: E731
    return vertical, horizontal


def surface_ends(grid: Grid, cells: np.ndarray, offset: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(S, 2, 2) ends (m, world xy) of the surfaces of ``cells``: each line through the cell's mean hit ``offset``
    (S, 2; m from the cell's lower corner) with unit ``normal`` (S, 2), clipped to its cell; where two surfaces end
    on one cell edge, both end at the mean of the two."""
    vertical, horizontal = _edge_keys(grid)
    c = grid.cell
    ij = np.stack([cells // grid.shape[1], cells % grid.shape[1]], 1)
    m = np.clip(offset, 1e-4 * c, (1 - 1e-4) * c)  # strictly inside, so the line has a length in the cell
    t = np.stack([normal[:, 1], -normal[:, 0]], 1)  # along the line
    with np.errstate(divide="ignore", invalid="ignore"):
        s0, s1 = -m / t, (c - m) / t  # where the line meets the cell's lower and upper edges, per axis
    lo, hi = np.minimum(s0, s1), np.maximum(s0, s1)
    rows = np.arange(len(m))
    enter, leave = np.argmax(lo, axis=1), np.argmin(hi, axis=1)  # the line is in the cell from lo to hi on both axes
    keys, sides = [], []
    for s, axis, upper in ((lo[rows, enter], enter, t[rows, enter] < 0), (hi[rows, leave], leave, t[rows, leave] > 0)):
        line = ij[rows, axis] + upper  # the grid line of the edge it crosses (in cells)
        keys.append(np.where(axis == 0, vertical(line, ij[:, 1]), horizontal(ij[:, 0], line)))
        sides.append((axis, line, ij[rows, 1 - axis] * c + m[rows, 1 - axis] + s * t[rows, 1 - axis]))
    _, at = np.unique(np.concatenate(keys), return_inverse=True)
    along = np.concatenate([side[2] for side in sides])
    along = (np.bincount(at, along) / np.bincount(at))[at].reshape(2, -1)  # m along each edge from the grid's origin
    ends = np.empty((len(m), 2, 2))
    for e, (axis, line, _) in enumerate(sides):
        ends[rows, e, axis] = line * c
        ends[rows, e, 1 - axis] = along[e]
    return np.asarray(grid.origin) + ends


def count_crossings(
    log: Log, grid: Grid, cells: np.ndarray, ends: np.ndarray, chunk: int = 64, workers: int = 1, progress=None
) -> tuple[np.ndarray, np.ndarray]:
    """Hits and pass-throughs of the surfaces of ``cells`` (S,), ascending, with ``ends`` (S, 2, 2), by tracing the
    log's returning beams through them.

    A beam hits the surface it crosses nearest to its return, when that lies within :data:`WINDOW` cells of the
    return (on either side: the beam may stop a little before the surface), and passes every other surface it
    crossed before that one. A beam that crosses none that near hits the surface of the cell its return lies in;
    a beam whose return lies in a box's cell hits no surface and passes those it crossed :data:`WINDOW` cells
    before its return or earlier. Cells are marched every quarter cell (:func:`~mi_lidar.planar.grid.march_cells`),
    ``chunk`` scans at a time on ``workers`` threads.

    Returns:
        (S,) hits and (S,) pass-throughs.
    """
    scans = [np.arange(first, min(first + chunk, log.shape[0])) for first in range(0, log.shape[0], chunk)]
    hits, passes = np.zeros(cells.size, np.int64), np.zeros(cells.size, np.int64)
    work = lambda k: _crossings(log, grid, cells, ends, scans[k])  # noqa: E731
    for k, (hit, passed) in enumerate(in_threads(work, range(len(scans)), workers)):
        hits += np.bincount(hit, minlength=cells.size)
        passes += np.bincount(passed, minlength=cells.size)
        if progress is not None:
            progress(scans[k][-1] + 1, log.shape[0])
    return hits, passes


def _crossings(log: Log, grid: Grid, cells: np.ndarray, ends: np.ndarray, scans: np.ndarray):
    """The surfaces (indices into ``cells``) ``scans``' beams hit, and those they passed (:func:`count_crossings`)."""
    window = WINDOW * grid.cell
    origin, direction, z = planar_beams(log, scans)
    returned = np.isfinite(z)
    o, d, r = origin[returned], direction[returned], z[returned]
    end = _index_in(cells, grid.cell_of(o + r[:, None] * d))
    ray, cell = march_cells(grid, o, d, r + window, grid.cell / 4)
    s = _index_in(cells, cell)
    ray, s = ray[s >= 0], s[s >= 0]
    ab, w = ends[s, 1] - ends[s, 0], ends[s, 0] - o[ray]
    cross = lambda u, v: u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]  # noqa: E731
    with np.errstate(divide="ignore", invalid="ignore"):
        t, u = (
            cross(w, ab) / cross(d[ray], ab),
            cross(w, d[ray]) / cross(d[ray], ab),
        )  # range on the beam, on the surface
    crossed = (t > 0) & (u >= 0) & (u <= 1)
    ray, s, t = ray[crossed], s[crossed], t[crossed]
    miss = np.abs(t - r[ray])
    near = (end[ray] >= 0) & (miss <= window)
    order = np.lexsort((miss, ~near, ray))  # per beam: the near crossings first, nearest first
    first = order[np.r_[True, ray[order][1:] != ray[order][:-1]]]
    first = first[near[first]]
    hit, at = end.copy(), r.copy()
    hit[ray[first]], at[ray[first]] = s[first], t[first]
    before = t < np.where(end >= 0, at, r - window)[ray]
    return hit[hit >= 0], s[before & (s != hit[ray])]


def _index_in(cells: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """Index into the ascending ``cells`` of each flat cell index ``flat``; -1 where it is not among them."""
    if not cells.size:
        return np.full(np.shape(flat), -1)
    k = np.minimum(np.searchsorted(cells, flat), cells.size - 1)
    return np.where(cells[k] == flat, k, -1)


def wall_faces(walls: WallMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The map's elements as a triangle mesh: each surface a quad, each box's side faces (a shared face once).

    Returns:
        (V, 3) vertices (m, world), (F, 3) triangles (two per quad or face) and (F,) their hit probabilities.
    """
    box = ~walls.surface
    vertical, horizontal = _edge_keys(walls.grid)
    nx, ny = walls.grid.shape
    i, j = walls.cells[box] // ny, walls.cells[box] % ny
    keys = np.concatenate([vertical(i, j), vertical(i + 1, j), horizontal(i, j), horizontal(i, j + 1)])
    survival = np.tile(0.5 * np.log1p(-walls.p_hit[box]), 4)  # log(1 - q) of the cell's face
    keys, at = np.unique(keys, return_inverse=True)
    p_face = -np.expm1(np.bincount(at, weights=survival))
    is_vertical = keys < (nx + 1) * ny
    h = keys - (nx + 1) * ny
    # the face's two grid corners (integer corner coordinates)
    a = np.where(is_vertical[:, None], np.stack([keys // ny, keys % ny], 1), np.stack([h // (ny + 1), h % (ny + 1)], 1))
    b = a + np.where(is_vertical[:, None], [0, 1], [1, 0])
    faces = np.asarray(walls.grid.origin) + np.stack([a, b], 1) * walls.grid.cell
    segments = np.concatenate([faces, walls.ends[walls.surface]])
    p = np.concatenate([p_face, walls.p_hit[walls.surface]])
    xy, index = np.unique(segments.reshape(-1, 2), axis=0, return_inverse=True)
    index = index.reshape(-1, 2)
    z = walls.plane_z + np.array([-HALF_HEIGHT, HALF_HEIGHT])
    vertices = np.concatenate([np.c_[xy, np.full(len(xy), z[0])], np.c_[xy, np.full(len(xy), z[1])]])
    lo_a, lo_b, hi_a, hi_b = index[:, 0], index[:, 1], index[:, 0] + len(xy), index[:, 1] + len(xy)
    triangles = np.concatenate([np.stack([lo_a, lo_b, hi_b], 1), np.stack([lo_a, hi_b, hi_a], 1)])
    return vertices, triangles, np.tile(p, 2)
