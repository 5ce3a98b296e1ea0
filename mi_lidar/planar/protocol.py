"""The real-planar protocol: splits, leave-out neighbourhoods, the map, and the traced beams of a log.

``PlanarProtocol`` (:mod:`mi_lidar.planar.settings`) holds the protocol's settings (``docs/benchmark_planar.md``): every
``test_every``-th scan is a test scan, the rest training; the map of query scan ``q`` leaves out the
scans within ``radius`` m *and* ``window`` s of it (and ``q`` itself); 5 cm ``occ3`` map; march to
40 m. :func:`prepare` builds the whole-log count map once and traces the test and training beams
through their own leave-out maps (:mod:`mi_lidar.planar.raymarch`).
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import EqualTimesWarning, LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.planar.grid import CountMap, Grid, check_moved, count_scans, in_threads, planar_beams
from mi_lidar.planar.raymarch import trace_scans
from mi_lidar.planar.settings import PlanarProtocol
from mi_lidar.planar.trace import PlanarTrace

MAX_CELLS = 2**28  # map cells: the count map keeps 24 bytes a cell (6 GB here) and needs twice that to build
TRIM = 5e-4  # share of the returns' ends left out of the map grid on each side of each axis (wild readings)


def map_grid(log: Log, cell: float, reach: float, trim: float = TRIM) -> Grid:
    """The map grid of a planar log: cells of ``cell`` m over its poses and the ends of its returns closer than
    ``reach`` m (the outermost ``trim`` of them on each side of each axis left out, so that a few wild readings do not
    widen it), with a 1 m margin.

    Raises:
        LogFormatError: no return closer than ``reach``, or a grid of more than :data:`MAX_CELLS` cells.
    """
    origin, direction, z = planar_beams(log)
    ends = (origin + np.nan_to_num(z)[..., None] * direction)[np.isfinite(z) & (z < reach)]
    if not ends.size:
        no_return = float(log.sensor.get("max_range_m", np.inf))
        code = f" and from the no-return value {no_return:g} m up" if np.isfinite(no_return) else ""
        raise LogFormatError(
            f"none of the log's {z.size:,} readings is a return closer than {reach:g} m (readings <= 0"
            f"{code} are no-returns), so there is no map: check the no-return value (--max-range) and that the "
            "ranges are in metres"
        )
    lo, hi = np.percentile(ends, [100 * trim, 100 * (1 - trim)], axis=0)
    inside = np.all((ends >= lo) & (ends <= hi), axis=1)
    grid = Grid.around(np.concatenate([ends[inside], log.poses[:, :2, 3]]), cell)
    if grid.size > MAX_CELLS:
        xy = log.poses[:, :2, 3]
        off = np.hypot(*(xy - np.median(xy, axis=0)).T)
        far = int(np.argmax(off))
        raise LogFormatError(
            f"the map would span {grid.shape[0] * grid.cell:,.0f} x {grid.shape[1] * grid.cell:,.0f} m "
            f"({grid.size:,} cells of {grid.cell:g} m, more than {MAX_CELLS:,}); scan {far + 1} of "
            f"{log.shape[0]} is at x={xy[far, 0]:g}, y={xy[far, 1]:g} m, {off[far]:,.0f} m from the median pose: "
            "check the log's poses (in metres?), or give a larger cell (--cell)"
        )
    return grid


def _where_and_when(log: Log, window: float) -> str:
    """Where and when a planar log's scans lie, and what to do when their leave-out maps (of ``window`` s) are empty:
    the end of a sentence."""
    xy, t = log.poses[:, :2, 3], log.times[:, 0, 0]
    dx, dy = np.ptp(xy, axis=0)
    return (
        f"the log's scans lie in a {dx:.2f} x {dy:.2f} m box over {np.ptp(t):.1f} s: give a longer log that passes "
        f"the same places more than {window:g} s apart, or a smaller radius or window (--radius, --window)"
    )


def _check_times(log: Log, protocol: PlanarProtocol) -> None:
    """Warn when the scans of ``log`` (two or more) all have one timestamp: every scan is then within the protocol's
    ``window`` s of every other, and the map of a scan leaves out every scan within ``radius`` m at any time."""
    t = log.times[:, 0, 0]
    if t.size < 2 or np.ptp(t) > 0:
        return
    warnings.warn(
        f"{log.sensor.get('source', 'the log')}: all {t.size} scans have the timestamp {t[0]:g} s (a converter that "
        f"wrote no times?), so each scan's map leaves out every scan within {protocol.radius:g} m of it whatever its "
        f"time, not only those within {protocol.window:g} s: a wider leave-out than the protocol's. Give the log its "
        "real timestamps",
        EqualTimesWarning,
        stacklevel=3,
    )


@dataclass
class PlanarData:
    """A planar log prepared for the benchmark: the map and the traced test and training beams.

    Attributes:
        log: the log.
        protocol: its settings.
        grid: the map grid.
        counts: the whole-log counts (leave-out maps of any query scan: :meth:`CountMap.leave_out`).
        test, train: the traced beams of the test and training scans.
        seconds: time spent per stage.
    """

    log: Log
    protocol: PlanarProtocol
    grid: Grid
    counts: CountMap
    test: PlanarTrace
    train: PlanarTrace
    seconds: dict


def prepare(log: Log, protocol: PlanarProtocol | None = None, progress=None, workers: int | None = None) -> PlanarData:
    """Count the whole-log map and trace every test and training beam through its leave-out map.

    Scans are counted and traced in batches on ``workers`` threads (default: one per CPU); the
    result does not depend on their number.

    Raises:
        LogFormatError: a log too short to split, one whose scans share one pose while they differ (no poses:
            :func:`~mi_lidar.planar.grid.check_moved`), or one without a map (:func:`map_grid`, and no beam meeting
            a wall in its leave-out map).

    Warns:
        EqualTimesWarning: the scans all have one timestamp: each map leaves out every scan within ``radius`` m.
    """
    protocol = protocol or PlanarProtocol()
    workers = workers or os.cpu_count() or 1
    say = progress or (lambda done, total, label: None)
    test_scans, train_scans = protocol.split(log.shape[0], log.shape[1])
    if np.unique(train_scans % 2).size < 2:  # the learned models fit on even training scans, check on odd ones
        raise LogFormatError(
            f"the log has {log.shape[0]} scan{'s' if log.shape[0] > 1 else ''}; the benchmark needs a test scan and "
            f"two training scans or more (every {protocol.test_every}-th scan is a test scan; the learned models "
            "choose their settings on the even training scans and check them on the odd ones): give a longer log"
        )
    check_moved(log, log.sensor.get("source", "the log"))
    _check_times(log, protocol)
    seconds, start = {}, time.perf_counter()
    grid = map_grid(log, protocol.cell, protocol.reach)
    counts = count_scans(
        log, grid, protocol.reach, progress=lambda d, n: say(d, n, "counting the map"), workers=workers
    )
    cmap = CountMap(counts)
    seconds["map"] = time.perf_counter() - start
    traces = {}

    def trace(batch: np.ndarray) -> PlanarTrace:
        excluded = [protocol.excluded(log, int(q)) for q in batch]
        return trace_scans(log, grid, cmap, batch, excluded, protocol.reach, protocol.max_segments, protocol.beyond)

    for name, scans in (("test", test_scans), ("train", train_scans)):
        start = time.perf_counter()
        batches = [scans[first : first + protocol.batch] for first in range(0, scans.size, protocol.batch)]
        parts, done = [], 0
        for batch, part in zip(batches, in_threads(trace, batches, workers)):
            parts.append(part)
            done += batch.size
            say(done, scans.size, f"tracing {name} beams")
        traces[name] = PlanarTrace.concatenate(parts)
        seconds[name] = time.perf_counter() - start
    for name, beams in traces.items():
        if not np.isfinite(beams.nominal).any():
            raise LogFormatError(
                f"no {name} beam of the log's {log.shape[0]} scans meets a wall in its map (the map of a scan "
                f"leaves out the scans within {protocol.radius:g} m and {protocol.window:g} s of it), and "
                + _where_and_when(log, protocol.window)
            )
    return PlanarData(
        log=log, protocol=protocol, grid=grid, counts=cmap, test=traces["test"], train=traces["train"], seconds=seconds
    )
