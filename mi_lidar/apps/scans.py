"""The states the planar applications run on, the real scans and the simulated scans at the same beams.

Every application of :mod:`mi_lidar.apps` runs on a :class:`PlanarStates` (the test scans of the
real-planar protocol, in log order: true poses, odometry, each scan's leave-out map, the nominal ray
cast) with one (T, N) range array per data source: the measured scans, or one scan sampled per
state from each simulator fitted on the training scans (:func:`planar_datasets`). Real and simulated
datasets differ only in the sensor model: same poses, same beams, same map.

Poses are planar ``(x, y, theta)`` (m, m, rad) of the laser in the map frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mi_lidar.planar.grid import Grid
from mi_lidar.planar.protocol import PlanarData
from mi_lidar.planar.raymarch import occupied

REACH = 40.0  # m: the protocol's march limit; returns beyond it are not used by the applications
CAP = 2.0  # m: a state's position error counts at most this much in a tracking objective (lost is lost)


def wrap(angle):
    """Angles (rad) wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ∘ b`` of (..., 3) planar poses: ``b`` expressed in the frame of ``a``, returned in ``a``'s parent frame."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap(a[..., 2] + b[..., 2]),
        ],
        axis=-1,
    )


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ∘ b`` of (..., 3) planar poses: the motion from ``a`` to ``b`` in the frame of ``a``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap(b[..., 2] - a[..., 2])], axis=-1)


def to_world(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, 2) ``points`` of the laser frame in the world frame of ``pose`` (3,)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return points @ np.array([[c, s], [-s, c]]) + pose[:2]


def scan_points(ranges: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(n, 2) laser-frame points of the returns of one scan (finite and closer than :data:`REACH`), in beam order."""
    keep = np.isfinite(ranges) & (ranges > 0) & (ranges < REACH)
    r, a = ranges[keep], angles[keep]
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


@dataclass
class ScanMaps:
    """The map each state is localized in: the occupied (``occ3``) cells of its scan's leave-out map.

    Attributes:
        grid: the map grid.
        start: (T + 1,) offsets of each state's cells in ``cells``.
        cells: flat indices of the occupied cells, state after state.
    """

    grid: Grid
    start: np.ndarray
    cells: np.ndarray

    def cells_of(self, t: int) -> np.ndarray:
        """Flat indices of the occupied cells of state ``t``."""
        return self.cells[self.start[t] : self.start[t + 1]]

    def points(self, t: int) -> np.ndarray:
        """(M, 2) world centres (m) of the occupied cells of state ``t``."""
        return self.grid.center(self.cells_of(t))

    def occupancy(self, t: int) -> np.ndarray:
        """(nx, ny) bool occupancy of state ``t``'s map."""
        mask = np.zeros(self.grid.size, bool)
        mask[self.cells_of(t)] = True
        return mask.reshape(self.grid.shape)


@dataclass
class PlanarStates:
    """The test states of a planar log (see the module docstring); arrays over T states and N beams.

    Attributes:
        scans: (T,) scan indices in the log.
        angles: (N,) beam angles in the laser frame, rad.
        poses: (T, 3) SLAM-corrected laser poses (the ground truth).
        odometry: (T, 3) odometry poses (in logs whose odometry is the corrected pose, the same).
        nominal: (T, N) ideal ray cast in each state's map, m (NaN: nothing within reach).
        maps: each state's leave-out map.
    """

    scans: np.ndarray
    angles: np.ndarray
    poses: np.ndarray
    odometry: np.ndarray
    nominal: np.ndarray
    maps: ScanMaps
    _memo: dict = field(default_factory=dict, repr=False)

    @property
    def n(self) -> int:
        return int(self.scans.size)

    def memo(self, key: tuple, build: Callable[[], object]):
        """What an application derives once from these states (a map index, a distance field), by ``key``."""
        if key not in self._memo:
            self._memo[key] = build()
        return self._memo[key]


def planar_pose(matrix: np.ndarray) -> np.ndarray:
    """(..., 3) planar poses of (..., 4, 4) transforms."""
    return np.stack([matrix[..., 0, 3], matrix[..., 1, 3], np.arctan2(matrix[..., 1, 0], matrix[..., 0, 0])], axis=-1)


def leave_out_maps(data: PlanarData, scans: np.ndarray, batch: int = 32) -> ScanMaps:
    """The occupied cells of the leave-out map of each of ``scans`` (the maps the simulators cast in)."""
    candidates = np.flatnonzero(data.counts.hits > 0)
    start, cells = [0], []
    for first in range(0, scans.size, batch):
        chunk = scans[first : first + batch]
        leave = data.counts.leave_out([data.protocol.excluded(data.log, int(q)) for q in chunk])
        query = np.repeat(np.arange(chunk.size), candidates.size)
        hits, passes = leave.counts(query, np.tile(candidates, chunk.size))
        occ = occupied(hits, passes).reshape(chunk.size, candidates.size)
        for row in occ:
            cells.append(candidates[row])
            start.append(start[-1] + int(row.sum()))
    return ScanMaps(grid=data.grid, start=np.asarray(start), cells=np.concatenate(cells) if cells else np.zeros(0, int))


def per_state(trace_scan: np.ndarray, trace_beam: np.ndarray, values: np.ndarray, scans: np.ndarray, n_beams: int):
    """(T, N) array of per-beam ``values`` of a trace (NaN where a beam is absent)."""
    out = np.full((scans.size, n_beams), np.nan)
    out[np.searchsorted(scans, trace_scan), trace_beam] = values
    return out


def planar_datasets(benchmark) -> tuple[PlanarStates, dict[str, np.ndarray]]:
    """The test states of a planar benchmark and the (T, N) ranges of each source (NaN: no return).

    Args:
        benchmark: a :class:`~mi_lidar.planar.benchmark.PlanarBenchmark` whose rows hold each
            simulator's sampled test scan.

    Returns:
        The states, and ``{"real": measured, <model name>: sampled, ...}``.
    """
    data = benchmark.data
    log, test = data.log, data.test
    scans = np.unique(test.scan)
    n_beams = log.shape[1]
    odometry = np.asarray(log.sensor.get("odometry", planar_pose(log.poses)), np.float64)[scans]
    states = PlanarStates(
        scans=scans,
        angles=np.arctan2(log.directions[0, :, 0, 1], log.directions[0, :, 0, 0]).astype(np.float64),
        poses=planar_pose(log.poses[scans]),
        odometry=odometry,
        nominal=per_state(test.scan, test.beam, test.nominal, scans, n_beams),
        maps=leave_out_maps(data, scans),
    )
    ranges = {"real": per_state(test.scan, test.beam, test.z, scans, n_beams)}
    for row in benchmark.rows:
        z, hit = row.sampled
        ranges[row.name] = per_state(test.scan, test.beam, np.where(hit, z, np.nan), scans, n_beams)
    return states, ranges


MOTION_NOISE = (0.02, 0.05, np.radians(1.0), 0.05)  # sigma_xy = a + b |d| (m), sigma_theta = c + d |dtheta| (rad)
START_NOISE = (0.1, np.radians(3.0))  # sigma of the initial pose guess: position (m), heading (rad)


def motion_sigma(u: np.ndarray) -> np.ndarray:
    """(..., 3) standard deviations of the noise added to (..., 3) odometry motions (:data:`MOTION_NOISE`)."""
    a, b, c, d = MOTION_NOISE
    xy = a + b * np.hypot(u[..., 0], u[..., 1])
    return np.stack([xy, xy, c + d * np.abs(u[..., 2])], axis=-1)


def noisy_run(states: PlanarStates, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One run's inputs: a noisy initial pose (3,) and noisy odometry motions (T - 1, 3) between states.

    The motions are the odometry's (``relative`` of consecutive odometry poses) plus Gaussian noise of
    :func:`motion_sigma`; a seed gives the same run on every dataset (common random numbers).
    """
    rng = np.random.default_rng(seed)
    xy, theta = START_NOISE
    start = states.poses[0] + rng.normal(0.0, 1.0, 3) * np.array([xy, xy, theta])
    u = relative(states.odometry[:-1], states.odometry[1:])
    return start, u + rng.normal(0.0, 1.0, u.shape) * motion_sigma(u)
