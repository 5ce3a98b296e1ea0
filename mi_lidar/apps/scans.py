"""The states the planar applications run on, the real scans and the simulated scans at the same beams.

Every application of :mod:`mi_lidar.apps` runs on a :class:`PlanarStates`: every scan of a planar log,
in log order (true poses, odometry, the nominal ray cast, the leave-out maps, the walls of the map),
with (S, T, N) ranges per data source: the measured scans (S = 1), or S scans sampled per state by each
simulator fitted on the protocol's training scans (:func:`planar_datasets`). Real and simulated
datasets differ only in the sensor model: same poses, same beams, same maps.

The trackers (registration, localization) run along the whole log, stretch after stretch of about
20 m (:func:`stretches`: each stretch is one filter run from a noisy start pose, so a filter that
loses track loses one stretch, not the rest of the log), with noisy odometry between consecutive
scans (:func:`noisy_runs`; the noise model is :data:`MOTION_NOISE`): run ``r`` of a stochastic
application uses the ``r``-th noise stream on every source and the ``r``-th simulated scan of a
simulator, so real and simulated runs are paired (common random numbers); :func:`paired_runs` adds
runs while the objective is uncertain.

Poses are planar ``(x, y, theta)`` (m, m, rad) of the laser in the map frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mi_lidar.apps.walls import map_walls
from mi_lidar.core.errors import ParameterError
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
    """The maps the states are localized in: the occupied (``occ3``) cells of leave-out maps, one per group of states.

    Attributes:
        grid: the map grid.
        start: (G + 1,) offsets of each map's cells in ``cells``.
        cells: flat indices of the occupied cells, map after map.
        of_state: (T,) the map of each state.
    """

    grid: Grid
    start: np.ndarray
    cells: np.ndarray
    of_state: np.ndarray

    def map_of(self, t: int) -> int:
        """The map of state ``t`` (states of one group share it, and what an application derives from it)."""
        return int(self.of_state[t])

    def cells_of(self, t: int) -> np.ndarray:
        """Flat indices of the occupied cells of state ``t``'s map."""
        g = self.map_of(t)
        return self.cells[self.start[g] : self.start[g + 1]]

    def points(self, t: int) -> np.ndarray:
        """(M, 2) world centres (m) of the occupied cells of state ``t``'s map."""
        return self.grid.center(self.cells_of(t))

    def occupancy(self, t: int) -> np.ndarray:
        """(nx, ny) bool occupancy of state ``t``'s map."""
        mask = np.zeros(self.grid.size, bool)
        mask[self.cells_of(t)] = True
        return mask.reshape(self.grid.shape)


@dataclass
class PlanarStates:
    """Every scan of a planar log as a state of the applications (see the module docstring); T states, N beams.

    Attributes:
        scans: (T,) scan indices in the log.
        test: (T,) the protocol's test scans (held out of every simulator's fit).
        angles: (N,) beam angles in the laser frame, rad.
        poses: (T, 3) SLAM-corrected laser poses (the ground truth).
        odometry: (T, 3) odometry poses (in logs whose odometry is the corrected pose, the same).
        nominal: (T, N) ideal ray cast in each state's leave-out map, m (NaN: nothing within reach).
        maps: the leave-out maps.
        walls: (W, 4) the walls of the whole-log map, ``x0, y0, x1, y1`` (m, world;
            :func:`~mi_lidar.apps.walls.map_walls`).
    """

    scans: np.ndarray
    test: np.ndarray
    angles: np.ndarray
    poses: np.ndarray
    odometry: np.ndarray
    nominal: np.ndarray
    maps: ScanMaps
    walls: np.ndarray
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


def leave_out_maps(data: PlanarData, groups: list[np.ndarray], batch: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells of one map per group of scans, leaving out what the map of any scan of the group leaves out.

    Returns:
        ``(start, cells)`` of :class:`ScanMaps`.
    """
    candidates = np.flatnonzero(data.counts.hits > 0)
    start, cells = [0], []
    for first in range(0, len(groups), batch):
        chunk = groups[first : first + batch]
        excluded = [np.unique(np.concatenate([data.protocol.excluded(data.log, int(q)) for q in g])) for g in chunk]
        leave = data.counts.leave_out(excluded)
        query = np.repeat(np.arange(len(chunk)), candidates.size)
        hits, passes = leave.counts(query, np.tile(candidates, len(chunk)))
        occ = occupied(hits, passes).reshape(len(chunk), candidates.size)
        for row in occ:
            cells.append(candidates[row].astype(np.int32))
            start.append(start[-1] + int(row.sum()))
    return np.asarray(start), np.concatenate(cells) if cells else np.zeros(0, np.int32)


def per_state(trace_scan: np.ndarray, trace_beam: np.ndarray, values: np.ndarray, scans: np.ndarray, n_beams: int):
    """(T, N) array of per-beam ``values`` of a trace (NaN where a beam is absent)."""
    out = np.full((scans.size, n_beams), np.nan)
    out[np.searchsorted(scans, trace_scan), trace_beam] = values
    return out


def planar_datasets(benchmark, samples: int = 8, seed: int = 0) -> tuple[PlanarStates, dict[str, np.ndarray]]:
    """Every scan of a planar benchmark's log as a state, and the ranges of each source at every state.

    The states' maps: the scans are grouped from one test scan to the next (the protocol's split), and
    each group is localized in one leave-out map that leaves out, for every scan of the group, what its
    own map leaves out (so no scan is ever matched against its own returns). Every simulator samples
    ``samples`` scans per state (seeds ``seed``, ``seed + 1``, ...; the first is the benchmark's), at the
    test scans and at the training scans it was fitted on.

    Args:
        benchmark: a :class:`~mi_lidar.planar.benchmark.PlanarBenchmark` whose rows hold each
            simulator's fitted model.
        samples: simulated scans per state and simulator.
        seed: seed of the first simulated scan.

    Returns:
        The states, and ``{"real": (1, T, N), <model name>: (samples, T, N), ...}`` float32 ranges
        (m; NaN: no return).
    """
    data = benchmark.data
    log, protocol = data.log, data.protocol
    scans = np.arange(log.shape[0])
    n_beams = log.shape[1]
    traces = (data.test, data.train)
    scan_of = np.concatenate([t.scan for t in traces])
    beam_of = np.concatenate([t.beam for t in traces])

    def gather(values: list[np.ndarray]) -> np.ndarray:
        return per_state(scan_of, beam_of, np.concatenate(values), scans, n_beams).astype(np.float32)

    test = scans % protocol.test_every == 0
    groups = np.cumsum(test) - 1
    start, cells = leave_out_maps(data, [scans[groups == g] for g in range(int(groups.max()) + 1)])
    empty = np.flatnonzero(np.diff(start) == 0)
    if empty.size:
        group = scans[groups == empty[0]]
        raise ParameterError(
            f"test_every={protocol.test_every}: the map of scans {group[0]} to {group[-1]} is empty: together they "
            f"leave out every scan within {protocol.radius:g} m and {protocol.window:g} s of one of them; lower "
            "test_every (--test-every) or the window (--window)"
        )
    whole = occupied(data.counts.hits, data.counts.passes).reshape(data.grid.shape)
    states = PlanarStates(
        scans=scans,
        test=test,
        angles=np.arctan2(log.directions[0, :, 0, 1], log.directions[0, :, 0, 0]).astype(np.float64),
        poses=planar_pose(log.poses),
        odometry=np.asarray(log.sensor.get("odometry", planar_pose(log.poses)), np.float64),
        nominal=gather([t.nominal for t in traces]).astype(np.float64),
        maps=ScanMaps(grid=data.grid, start=start, cells=cells, of_state=groups),
        walls=map_walls(whole, data.grid),
    )
    ranges = {"real": gather([t.z for t in traces])[None]}
    for row in benchmark.rows:
        train, test_beams, model = row.engine
        draws = []
        for k in range(samples):
            sampled = [beams.sample(model, seed + k) for beams in (test_beams, train)]
            draws.append(gather([np.where(hit, z, np.nan) for z, hit in sampled]))
        ranges[row.name] = np.stack(draws)
    return states, ranges


MOTION_NOISE = (0.02, 0.05, np.radians(1.0), 0.05)  # sigma_xy = a + b |d| (m), sigma_theta = c + d |dtheta| (rad)
START_NOISE = (0.1, np.radians(3.0))  # sigma of the initial pose guess: position (m), heading (rad)


def motion_sigma(u: np.ndarray) -> np.ndarray:
    """(..., 3) standard deviations of the noise added to (..., 3) odometry motions (:data:`MOTION_NOISE`)."""
    a, b, c, d = MOTION_NOISE
    xy = a + b * np.hypot(u[..., 0], u[..., 1])
    return np.stack([xy, xy, c + d * np.abs(u[..., 2])], axis=-1)


def _indices(runs) -> np.ndarray:
    """Run indices: ``runs`` itself, or ``0 .. runs - 1`` for a count."""
    return np.arange(runs) if np.ndim(runs) == 0 else np.asarray(runs, np.int64)


def stretches(states: PlanarStates, length: float, max_states: int | None = None) -> list[tuple[int, int]]:
    """The log cut into consecutive stretches of about ``length`` m of travel: ``[(first, stop), ...]`` state indices.

    A stretch ends at the first state at least ``length`` m of path (along the true poses) after its first
    state; the last one ends with the log. With ``max_states``, a log with more states keeps evenly spaced
    stretches holding at most that many states (what bounds a tracker's cost on long logs).
    """
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(states.poses[:, :2], axis=0).T))])
    cuts, first = [], 0
    while first < states.n:
        stop = int(np.searchsorted(path, path[first] + length, side="left")) + 1
        stop = min(max(stop, first + 2), states.n)
        cuts.append((first, stop))
        first = stop
    if max_states is not None and states.n > max_states:
        size = np.array([b - a for a, b in cuts])
        keep = max(1, int(len(cuts) * max_states / states.n))
        while keep > 1 and size[np.linspace(0, len(cuts) - 1, keep).astype(int)].sum() > max_states:
            keep -= 1
        cuts = [cuts[k] for k in np.unique(np.linspace(0, len(cuts) - 1, keep).astype(int))]
    return cuts


def noisy_runs(states: PlanarStates, runs, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The inputs of filter runs: noisy start poses at every state (R, T, 3) and noisy odometry motions (R, T - 1, 3).

    The motions are the odometry's (``relative`` of consecutive odometry poses) plus Gaussian noise of
    :func:`motion_sigma`; a start pose is the true one plus Gaussian noise of :data:`START_NOISE` (a
    filter that starts at a state uses it). Run ``r`` draws from its own stream of ``seed``, so it is
    the same on every dataset and whatever the other runs (common random numbers).

    Args:
        runs: the run indices (R,), or their count (runs ``0 .. R - 1``).
    """
    u = relative(states.odometry[:-1], states.odometry[1:])
    xy, theta = START_NOISE
    starts, motions = [], []
    for run in _indices(runs):
        rng = np.random.default_rng([seed, int(run)])
        starts.append(states.poses + rng.normal(0.0, 1.0, states.poses.shape) * np.array([xy, xy, theta]))
        motions.append(u + rng.normal(0.0, 1.0, u.shape) * motion_sigma(u))
    return np.asarray(starts), np.asarray(motions)


def run_ranges(ranges: np.ndarray, runs) -> np.ndarray:
    """(R, T, N) ranges of runs (indices or a count) of (S, T, N) datasets or one (T, N); run ``r`` sees ``r mod S``."""
    ranges = np.asarray(ranges)
    if ranges.ndim == 2:
        ranges = ranges[None]
    return ranges[_indices(runs) % ranges.shape[0]]


def paired_runs(batch, runs: int, max_runs: int, target_se: float) -> dict[str, np.ndarray]:
    """Filter runs batch after batch until the per-run objective is known well enough.

    ``batch(indices)`` runs the filter for run indices (R,) and returns per-run arrays (leading axis R)
    with ``"objective"`` (R,) among them. Batches of ``runs`` runs (0 .. runs - 1, then the next ``runs``,
    ...) are added while the standard error of the mean objective exceeds ``target_se`` and fewer than
    ``max_runs`` have run: a setting where the filter sometimes diverges, and whose objective is then a
    coin toss between tracking and lost, gets more runs than one that always tracks.

    Returns:
        The per-run arrays of every run, concatenated.
    """
    parts: list[dict] = []
    done = 0
    while True:
        parts.append(batch(np.arange(done, done + runs)))
        done += runs
        objective = np.concatenate([p["objective"] for p in parts])
        error = np.std(objective, ddof=1) / np.sqrt(objective.size) if objective.size > 1 else 0.0
        if error <= target_se or done >= max_runs:
            return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def stretch_mask(cuts, n_states: int) -> np.ndarray:
    """(T,) True at the states inside the stretches ``cuts`` (``(first, stop)`` pairs) a tracker ran along."""
    used = np.zeros(n_states, bool)
    for first, stop in cuts:
        used[first:stop] = True
    return used


def tracker_metrics(done: dict[str, np.ndarray]) -> dict:
    """J (mean over runs of the per-run objective), the per-run objectives, the divergence rate (share of
    state errors above 1 m) and the mean heading error (deg) of a tracker's :func:`paired_runs`."""
    return {
        "J": float(done["objective"].mean()),
        "J_runs": done["objective"].tolist(),
        "divergence": float(np.mean(done["errors"] > 1.0)),
        "heading_error_deg": float(np.degrees(done["headings"].mean())),
    }


@dataclass
class Tracker(ABC):
    """A tracker (registration, localization): a filter run along the log's stretches, and its run settings.

    Attributes:
        runs: filter runs per batch (each with its own noise, the same on every dataset).
        max_runs: most runs per evaluation: batches are added while the standard error of J exceeds
            ``target_se`` (:func:`paired_runs`).
        target_se: standard error of J (m) that stops adding runs.
        stretch: travel (m) of one filter run: the log is cut into stretches of about this length
            (:func:`stretches`), each filtered from its own noisy start pose.
        max_states: on a longer log, evenly spaced stretches holding at most this many states are run.
    """

    runs: int = 8
    max_runs: int = 32
    target_se: float = 0.01
    stretch: float = 20.0
    max_states: int = 1000

    @abstractmethod
    def filter(self, alpha: dict, states: PlanarStates, ranges: np.ndarray, runs: np.ndarray) -> dict:
        """Run the filter along every stretch for run indices ``runs`` (R,) with setting ``alpha``.

        Returns:
            Per-run arrays (leading axis R): ``"objective"`` (R,), the state errors ``"errors"`` (m) and
            ``"headings"`` (rad), and what else the tracker reports.
        """

    def filter_runs(self, alpha: dict, states: PlanarStates, ranges: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`filter` on ``ranges`` ((S, T, N) or (T, N)), batch after batch until J is known to
        ``target_se`` (:func:`paired_runs`); the per-run arrays of every run."""
        return paired_runs(
            lambda runs: self.filter(alpha, states, ranges, runs), self.runs, self.max_runs, self.target_se
        )


def scan_statistics(states: PlanarStates, ranges: np.ndarray) -> dict:
    """What a source's scans contain, against the nominal ray cast at the same states (every sampled dataset pooled).

    Returns:
        ``no_return`` share of beams; ``short`` and ``long``: share of beams with a nominal range that
        return more than 0.5 m before or after it; ``median_abs_error`` (m) of the other returns;
        ``neighbour_difference`` (m): median of ``|e_b - e_b+1|`` over neighbouring beams that both
        return within 0.5 m of their nominal range (``e = z - nominal``; how smooth a surface's points
        are); ``outlier_run``: mean length (beams) of the runs of no-return, short or long beams.
    """
    z = run_ranges(ranges, np.shape(ranges)[0] if np.ndim(ranges) == 3 else 1).astype(np.float64)
    nominal = np.broadcast_to(states.nominal, z.shape)
    met = np.isfinite(nominal)
    e = z - nominal
    hit = np.isfinite(z)
    near = hit & met & (np.abs(np.nan_to_num(e, nan=np.inf)) <= 0.5)
    both = near[..., 1:] & near[..., :-1]
    outlier = ~hit | (met & hit & ~near)
    flat = outlier.reshape(-1, outlier.shape[-1])
    edges = np.diff(np.concatenate([np.zeros((flat.shape[0], 1), int), flat, np.zeros((flat.shape[0], 1), int)], 1), 1)
    return {
        "no_return": float(np.mean(~hit)),
        "short": float(np.mean(met & hit & (e < -0.5))),
        "long": float(np.mean(met & hit & (e > 0.5))),
        "median_abs_error": float(np.median(np.abs(e[near]))) if near.any() else float("nan"),
        "neighbour_difference": float(np.median(np.abs(np.diff(e, axis=-1))[both])) if both.any() else float("nan"),
        "outlier_run": float(flat.sum() / max(int(np.sum(edges == 1)), 1)),
    }
