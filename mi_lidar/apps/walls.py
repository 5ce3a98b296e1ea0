"""The walls of an occupancy map as line segments, and the pieces of them a state sees: the line detection's reference.

The reference does not come from any scan or scan detector. :func:`map_walls` finds straight walls in
the map itself by region growing on its occupied cells: every occupied cell gets a local line by PCA
of the occupied cells within :data:`RADIUS` (line-like when at least 4 cells and the smaller
eigenvalue is at most :data:`LINEAR` times the larger: walls drawn a few cells thick are line-like);
from the most line-like cell on, a region takes neighbouring line-like cells (up to 2 cells away, bridging one-cell
holes) whose line is within :data:`ANGLE` of the region's and whose centre lies within :data:`THICK`
cells of it (the region's line is refitted as it grows); regions on one line with at most 3 cells
between them are joined. A region longer than ``min_length`` is a wall: its total
least-squares line, between the extreme projections of its cells.

:func:`visible_walls` cuts the walls a state sees out of its nominal scan (the ideal ray cast in its
leave-out map): each nominal hit within :data:`NEAR` of a wall belongs to it, and every run of at
least ``min_beams`` consecutive beams on the same wall is one visible piece, between the projections
of its first and last hit on the wall. A wall seen on both sides of an occluder is two pieces, as a
detector on the scan would see it.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.planar.grid import Grid

RADIUS = 3  # cells: the neighbourhood of a cell's local line (15 cm on the protocol's 5 cm grid)
ANGLE = np.radians(10.0)  # largest angle between a cell's local line and its region's line
LINEAR = 0.3  # line-like: the smaller PCA eigenvalue of a cell's neighbourhood is at most this times the larger
THICK = 2.0  # cells: a cell joins a wall within this distance of its line (maps draw walls 2-4 cells thick)
NEAR = 0.1  # m: a nominal hit this close to a wall (and within its extent) belongs to it
DISC = np.array(
    [
        (dx, dy)
        for dx in range(-RADIUS, RADIUS + 1)
        for dy in range(-RADIUS, RADIUS + 1)
        if dx * dx + dy * dy <= RADIUS * RADIUS
    ]
)
STEP = np.array([(dx, dy) for dx in range(-2, 3) for dy in range(-2, 3) if 0 < dx * dx + dy * dy <= 4])


def _local_lines(occupancy: np.ndarray, ij: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local line at each of (M, 2) occupied cells: direction (rad), eigenvalue ratio, and whether it is line-like."""
    around = ij[:, None, :] + DISC[None]
    inside = np.all((around >= 0) & (around < np.asarray(occupancy.shape)), axis=-1)
    occ = inside & occupancy[np.where(inside, around[..., 0], 0), np.where(inside, around[..., 1], 0)]
    n = occ.sum(axis=1)
    mean = (DISC[None] * occ[..., None]).sum(axis=1) / np.maximum(n, 1)[:, None]
    centred = (DISC[None] - mean[:, None, :]) * occ[..., None]
    cxx, cyy = (centred[..., 0] ** 2).sum(1), (centred[..., 1] ** 2).sum(1)
    cxy = (centred[..., 0] * centred[..., 1]).sum(1)
    root = np.sqrt((0.5 * (cxx - cyy)) ** 2 + cxy**2)
    big, small = 0.5 * (cxx + cyy) + root, 0.5 * (cxx + cyy) - root
    ratio = np.where(big > 0, small / np.where(big > 0, big, 1.0), np.inf)
    return 0.5 * np.arctan2(2 * cxy, cxx - cyy), ratio, (n >= 4) & (ratio <= LINEAR)


def _fit(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (2,) and unit direction (2,) of the total-least-squares line through (n, 2) points."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    return centre, vt[0]


def _segment(points: np.ndarray, cell: float) -> np.ndarray:
    """The segment (4,) of the total-least-squares line through (n, 2) cell centres, over their extent + half a cell."""
    centre, direction = _fit(points)
    along = (points - centre) @ direction
    return np.concatenate(
        [centre + (along.min() - 0.5 * cell) * direction, centre + (along.max() + 0.5 * cell) * direction]
    )


def _merge_collinear(regions: list[np.ndarray], centres: np.ndarray, cell: float) -> list[np.ndarray]:
    """Regions joined while two lie on one line (within :data:`ANGLE` and :data:`THICK`) at most 3 cells apart."""
    regions = list(regions)
    lines = [_fit(centres[m]) for m in regions]
    i = 0
    while i < len(regions):
        j = i + 1
        while j < len(regions):
            if abs(lines[i][1][0] * lines[j][1][1] - lines[i][1][1] * lines[j][1][0]) <= np.sin(ANGLE):
                both = np.concatenate([regions[i], regions[j]])
                c, d = _fit(centres[both])
                rel = centres[both] - c
                a, b = (centres[regions[i]] - c) @ d, (centres[regions[j]] - c) @ d
                close = np.max(np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0])) <= THICK * cell
                if close and max(a.min(), b.min()) - min(a.max(), b.max()) <= 3 * cell:
                    regions[i], lines[i] = both, (c, d)
                    del regions[j], lines[j]
                    j = i + 1
                    continue
            j += 1
        i += 1
    return regions


def map_walls(occupancy: np.ndarray, grid: Grid, min_length: float = 0.5) -> np.ndarray:
    """(W, 4) wall segments ``x0, y0, x1, y1`` (m, world frame) of an (nx, ny) occupancy grid (module docstring)."""
    ij = np.argwhere(occupancy)
    if ij.shape[0] == 0:
        return np.zeros((0, 4))
    angle, ratio, linear = _local_lines(occupancy, ij)
    slot = np.full(occupancy.shape, -1, np.int64)
    slot[ij[:, 0], ij[:, 1]] = np.arange(ij.shape[0])
    centres = np.asarray(grid.origin) + (ij + 0.5) * grid.cell
    region = np.full(ij.shape[0], -1, np.int64)
    regions = []
    seeds = np.flatnonzero(linear)
    for seed in seeds[np.argsort(ratio[seeds], kind="stable")]:
        if region[seed] >= 0:
            continue
        region[seed] = seed
        members, frontier = [seed], [seed]
        centre, direction = centres[seed], np.array([np.cos(angle[seed]), np.sin(angle[seed])])
        refit = 8
        while frontier:
            around = ij[frontier][:, None, :] + STEP[None]
            around = around.reshape(-1, 2)
            inside = np.all((around >= 0) & (around < np.asarray(occupancy.shape)), axis=1)
            near = np.unique(slot[around[inside, 0], around[inside, 1]])
            near = near[(near >= 0)]
            near = near[(region[near] < 0) & linear[near]]
            turn = np.abs(np.sin(angle[near] - np.arctan2(direction[1], direction[0])))
            rel = centres[near] - centre
            offset = np.abs(rel[:, 0] * direction[1] - rel[:, 1] * direction[0])
            take = near[(turn < np.sin(ANGLE)) & (offset <= THICK * grid.cell)]
            region[take] = seed
            members += take.tolist()
            frontier = take.tolist()
            if len(members) >= refit:
                centre, direction = _fit(centres[members])
                refit = 2 * len(members)
        if len(members) >= 4:
            regions.append(np.asarray(members))
    walls = [_segment(centres[m], grid.cell) for m in _merge_collinear(regions, centres, grid.cell)]
    walls = [w for w in walls if np.hypot(w[2] - w[0], w[3] - w[1]) >= min_length]
    return np.asarray(walls).reshape(-1, 4)


def visible_walls(
    walls: np.ndarray, pose: np.ndarray, nominal: np.ndarray, angles: np.ndarray, min_beams: int = 5
) -> np.ndarray:
    """(V, 4) pieces of ``walls`` (W, 4) seen from ``pose`` (3,), ``x0, y0, x1, y1`` (m, world frame; module docstring).

    Args:
        walls: the map's walls (:func:`map_walls`).
        pose: the laser pose ``x, y, theta`` (m, rad).
        nominal: (N,) nominal ranges of the state's beams (m; NaN: nominal miss).
        angles: (N,) beam angles in the laser frame (rad).
        min_beams: fewest consecutive beams on a wall that make a visible piece.
    """
    if len(walls) == 0:
        return np.zeros((0, 4))
    c, s = np.cos(pose[2] + angles), np.sin(pose[2] + angles)
    hits = pose[:2] + np.nan_to_num(nominal)[:, None] * np.stack([c, s], axis=1)  # (N, 2)
    start, vector = walls[:, :2], walls[:, 2:] - walls[:, :2]
    length = np.maximum(np.hypot(vector[:, 0], vector[:, 1]), 1e-9)
    unit = vector / length[:, None]
    rel = hits[:, None, :] - start[None]
    along = np.sum(rel * unit[None], axis=-1)
    offset = np.abs(rel[..., 0] * unit[None, :, 1] - rel[..., 1] * unit[None, :, 0])
    ok = (offset <= NEAR) & (along >= -NEAR) & (along <= length[None] + NEAR) & np.isfinite(nominal)[:, None]
    wall = np.where(ok.any(axis=1), np.argmin(np.where(ok, offset, np.inf), axis=1), -1)
    edges = np.flatnonzero(np.diff(np.concatenate([[-2], wall, [-2]])) != 0)
    pieces = []
    for a, b in zip(edges[:-1], edges[1:]):
        w = wall[a]
        if w < 0 or b - a < min_beams:
            continue
        ends = start[w] + np.clip(along[[a, b - 1], w], 0.0, length[w])[:, None] * unit[w]
        pieces.append(ends.ravel())
    return np.asarray(pieces).reshape(-1, 4)
