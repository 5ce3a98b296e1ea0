"""Planar states of the independent test room (tests/planar/world.py) built directly, without the benchmark.

The map is the room's walls rasterized on a 5 cm grid centred on them (every cell a wall crosses is occupied); the
ranges are cast against the walls (the glass pane is left out) with Gaussian noise and, optionally,
a share of short returns from unmapped clutter.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.apps.scans import PlanarStates, ScanMaps
from mi_lidar.io.carmen import beam_angles
from mi_lidar.planar.grid import Grid
from tests.planar.world import WALLS, cast, poses

GRID = Grid(origin=(-1.025, -1.025), cell=0.05, shape=(280, 200))


def wall_cells(walls: np.ndarray = WALLS) -> np.ndarray:
    """Flat indices of the cells the walls cross."""
    cells = []
    for x0, y0, x1, y1 in walls:
        t = np.linspace(0.0, 1.0, int(np.hypot(x1 - x0, y1 - y0) / 0.005) + 2)
        cells.append(GRID.cell_of(np.stack([x0 + t * (x1 - x0), y0 + t * (y1 - y0)], 1)))
    return np.unique(np.concatenate(cells))


def cast_scans(states_poses: np.ndarray, angles: np.ndarray, walls: np.ndarray = WALLS) -> np.ndarray:
    """(T, N) noise-free ranges (m) from each pose to the walls (inf: nothing)."""
    out = np.empty((len(states_poses), angles.size))
    for t, (x, y, heading) in enumerate(states_poses):
        a = heading + angles
        out[t] = cast(np.repeat([[x, y]], angles.size, 0), np.stack([np.cos(a), np.sin(a)], 1), walls).min(1)
    return out


def room_states(scans: int = 40, beams: int = 181) -> PlanarStates:
    """States along the robot's loop in the room (all test states); each maps the whole room, its walls the room's."""
    truth = poses(scans)
    angles = beam_angles(beams)
    cells = wall_cells()
    return PlanarStates(
        scans=np.arange(scans),
        test=np.ones(scans, bool),
        angles=angles,
        poses=truth,
        odometry=truth.copy(),
        nominal=cast_scans(truth, angles),
        maps=ScanMaps(grid=GRID, start=np.array([0, cells.size]), cells=cells, of_state=np.zeros(scans, np.int64)),
        walls=WALLS.copy(),
    )


def room_ranges(states: PlanarStates, sigma: float, short: float = 0.0, seed: int = 0) -> np.ndarray:
    """(T, N) measured ranges: the nominal ones with noise ``sigma`` (m); a ``short`` share return uniformly short."""
    rng = np.random.default_rng(seed)
    z = states.nominal + rng.normal(0.0, sigma, states.nominal.shape)
    clutter = rng.random(z.shape) < short
    return np.where(clutter, z * rng.uniform(0.1, 0.9, z.shape), z)
