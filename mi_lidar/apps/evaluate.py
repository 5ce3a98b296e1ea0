"""``mi-lidar evaluate-apps``: the planar applications on real and simulated scans of a CARMEN log.

The flow: the real-planar benchmark (:func:`~mi_lidar.planar.benchmark.run_planar_benchmark`) fits
each simulator on the training scans; :func:`planar_datasets` makes every scan of the log a state and
samples ``runs`` scans per state from each simulator; every application is run on every dataset at
the prior draws and along the development paths (:func:`~mi_lidar.apps.risk.evaluate_application`),
``runs`` times where it is stochastic (run ``r`` with the same noise on every dataset and a
simulator's ``r``-th sampled scans).

Caches (in ``OUT/cache``): ``datasets.npz`` (states and scans; keyed by the log's SHA-256, the
protocol, the simulators, the runs, the seed and the code, :func:`~mi_lidar.apps.cache.cache_key`)
and ``objectives-<application>.json`` (every evaluated ``J``, keyed by the same and the
application's settings), so a rerun, or a run stopped half-way, resumes where it was.
"""

from __future__ import annotations

import multiprocessing
import queue
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.apps.cache import cache_key, load_datasets, save_datasets
from mi_lidar.apps.lines import LineDetection
from mi_lidar.apps.localization import ParticleFilter
from mi_lidar.apps.registration import ScanToMapEKF
from mi_lidar.apps.risk import AppResult, Objectives, evaluate_application
from mi_lidar.apps.scans import MOTION_NOISE, PlanarStates, ScanMaps, planar_datasets, scan_statistics
from mi_lidar.core.atomic import output_folder
from mi_lidar.core.params import choose_names
from mi_lidar.core.strict_json import dumps
from mi_lidar.planar.benchmark import MODELS
from mi_lidar.planar.grid import Grid
from mi_lidar.planar.protocol import PlanarProtocol

SIMULATORS = ("M0", "M1", "P-Reg", "NP-Reg", "mi-lidar")


def applications(runs: int = 8) -> list:
    """The planar applications, each run ``runs`` times per evaluation where it is stochastic."""
    return [ScanToMapEKF(runs=runs), ParticleFilter(runs=runs), LineDetection()]


@dataclass
class AppsEvaluation:
    """Result of :func:`evaluate_log`.

    Attributes:
        source: the log file.
        states: the test states.
        simulators: the simulators' names.
        results: one :class:`AppResult` per application.
        benchmark: the benchmark's rows of the simulators (NLL and sample realism).
        seconds: time per stage.
        runs: runs of the stochastic applications per setting.
        draws: prior draws of the risk.
        ranges: the datasets (for the report's scan figure).
        scans: ``{source: scan_statistics}`` of every dataset against the nominal ray cast.
    """

    source: str
    states: PlanarStates
    simulators: tuple[str, ...]
    results: list[AppResult]
    benchmark: list[dict]
    seconds: dict
    runs: int = 1
    draws: int = 0
    ranges: dict | None = field(default=None, repr=False)
    scans: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        a, b, c, d = MOTION_NOISE
        return {
            "log": self.source,
            "states": self.states.n,
            "test_states": int(self.states.test.sum()),
            "beams": int(self.states.angles.size),
            "runs": self.runs,
            "draws": self.draws,
            "odometry_noise": f"Gaussian per consecutive-scan motion (d, dtheta): sigma_xy = {a:g} m + {b:g} |d|, "
            f"sigma_theta = {np.degrees(c):g} deg + {d:g} |dtheta|",
            "simulators": list(self.simulators),
            "scans": self.scans,
            "benchmark": self.benchmark,
            "applications": [r.to_json() for r in self.results],
            "seconds": self.seconds,
        }


def _key(
    path: Path, protocol: PlanarProtocol, simulators: tuple[str, ...], runs: int, seed: int, max_range, message
) -> str:
    settings = {
        "protocol": protocol.__dict__,
        "sim": simulators,
        "runs": runs,
        "seed": seed,
        "max": max_range,
    }
    if message is not None:  # a log read from other laser lines; the default keeps its key
        settings["message"] = message
    return cache_key(path, settings)


def _state_arrays(states: PlanarStates) -> dict:
    grid = states.maps.grid
    return {
        "scans": states.scans,
        "test": states.test,
        "angles": states.angles,
        "poses": states.poses,
        "odometry": states.odometry,
        "nominal": states.nominal,
        "map_start": states.maps.start,
        "map_cells": states.maps.cells,
        "map_of_state": states.maps.of_state,
        "walls": states.walls,
        "grid": np.array([*grid.origin, grid.cell, *grid.shape], np.float64),
    }


def _states(z: dict) -> PlanarStates:
    g = z["grid"]
    grid = Grid(origin=(float(g[0]), float(g[1])), cell=float(g[2]), shape=(int(g[3]), int(g[4])))
    return PlanarStates(
        scans=z["scans"],
        test=z["test"],
        angles=z["angles"],
        poses=z["poses"],
        odometry=z["odometry"],
        nominal=z["nominal"],
        maps=ScanMaps(grid=grid, start=z["map_start"], cells=z["map_cells"], of_state=z["map_of_state"]),
        walls=z["walls"],
    )


def app_settings(app) -> str:
    """What an application's cached objectives depend on besides the datasets.

    Not the draws: a rerun with more draws reuses every objective already evaluated.
    """
    return dumps([app.name, repr(app)])


def _run_one(app, states, ranges, file: Path, key: str, draws: int, seed: int, progress=None):
    """One application's :class:`AppResult` (cached in ``file``), and the wall and CPU seconds it took."""
    t0, c0 = time.perf_counter(), time.process_time()
    result = evaluate_application(app, Objectives(states, ranges, file, key, progress), m=draws, seed=seed)
    return result, time.perf_counter() - t0, time.process_time() - c0


def evaluate_datasets(
    states: PlanarStates,
    ranges: dict[str, np.ndarray],
    out: Path,
    source: str = "",
    benchmark: list[dict] | None = None,
    key: str = "",
    draws: int = 16,
    runs: int = 8,
    seed: int = 0,
    workers: int = 1,
    progress=None,
    spent: dict | None = None,
) -> AppsEvaluation:
    """Evaluate every planar application on datasets of the same states and write the report to ``out``.

    Args:
        states: the states.
        ranges: ``{"real": (1, T, N), <simulator>: (S, T, N), ...}`` ranges (m, NaN: no return); run
            ``r`` of a stochastic application sees a source's dataset ``r mod S``.
        out: report folder (``apps.json``, ``apps.html``, PNGs, ``cache/objectives.json``).
        source: the log file, for the report.
        benchmark: the simulators' benchmark rows (NLL and sample realism), for the report.
        key: what the datasets are (the objectives cache is reused only for the same key).
        draws: prior draws of the risk.
        runs: runs of each stochastic application per evaluation.
        seed: seed of the draws.
        workers: processes running the applications side by side (each caches its own objectives).
        progress: optional ``progress(done, total, label)``.
        spent: wall and CPU seconds of earlier stages (``{"datasets": s, "datasets_cpu": s}``), for the totals.
    """
    from mi_lidar.apps.report import write_report

    say = progress or (lambda done, total, label: None)
    (out / "cache").mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    jobs = [
        (app, out / "cache" / f"objectives-{app.name}.json", f"{key}|{app_settings(app)}") for app in applications(runs)
    ]
    results, seconds = [], {}
    total = (draws + 40) * len(ranges) * len(jobs)  # evaluations, roughly: draws and paths of every source
    done = [0]

    def tick(label: str) -> None:
        done[0] += 1
        say(min(done[0], total), total, f"evaluating {label}")

    if workers > 1:
        context = multiprocessing.get_context("fork")
        with context.Manager() as manager, ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            labels = manager.Queue()
            futures = [
                pool.submit(_run_one, app, states, ranges, file, app_key, draws, seed, labels.put)
                for app, file, app_key in jobs
            ]
            while not all(f.done() for f in futures):
                try:
                    tick(labels.get(timeout=0.5))
                except queue.Empty:
                    continue
            outcomes = [f.result() for f in futures]
    else:
        outcomes = [_run_one(app, states, ranges, file, app_key, draws, seed, tick) for app, file, app_key in jobs]
    for (app, _, _), (result, wall, cpu) in zip(jobs, outcomes):
        results.append(result)
        seconds[app.name], seconds[f"{app.name}_cpu"] = wall, cpu
    seconds["applications"] = time.perf_counter() - start
    earlier = spent or {"datasets": 0.0, "datasets_cpu": 0.0}
    seconds = {**earlier, **seconds, "total": earlier["datasets"] + seconds["applications"]}
    seconds["total_cpu"] = earlier["datasets_cpu"] + sum(seconds[f"{app.name}_cpu"] for app, _, _ in jobs)
    simulators = tuple(name for name in ranges if name != "real")
    scans = {name: scan_statistics(states, value) for name, value in ranges.items()}
    evaluation = AppsEvaluation(
        source, states, simulators, results, benchmark or [], seconds, runs, draws, ranges, scans
    )
    write_report(evaluation, out)
    return evaluation


def evaluate_log(
    path: str | Path,
    out: str | Path,
    max_range: float | None = None,
    protocol: PlanarProtocol | None = None,
    simulators: tuple[str, ...] = SIMULATORS,
    draws: int = 16,
    runs: int = 8,
    seed: int = 0,
    workers: int = 1,
    progress=None,
    message: str | None = None,
) -> AppsEvaluation:
    """Simulate the test states of a CARMEN log with each simulator, then :func:`evaluate_datasets`.

    Args:
        path: a SLAM-corrected CARMEN log.
        out: report folder (``apps.json``, ``apps.html``, PNGs, ``cache/``).
        max_range: the sensor's no-return value (m); default: detected from the log.
        protocol: the real-planar protocol's settings.
        simulators: models of the planar benchmark to simulate with.
        draws: prior draws of the risk.
        runs: runs of each stochastic application per evaluation, and scans sampled per state by each
            simulator.
        seed: seed of the sampled scans and of the draws.
        workers: processes running the applications side by side.
        progress: optional ``progress(done, total, label)``.
        message: the laser lines to read (:func:`~mi_lidar.io.carmen.read_carmen`; default: FLASER, else
            ROBOTLASER1).
    """
    from mi_lidar.io.dispatch import read_any
    from mi_lidar.planar.benchmark import run_planar_benchmark

    simulators = choose_names(simulators, MODELS, "evaluate-apps: unknown simulators")
    path, out = Path(path), Path(out)
    protocol = protocol or PlanarProtocol()
    start, cpu = time.perf_counter(), time.process_time()
    key = _key(path, protocol, tuple(simulators), runs, seed, max_range, message)
    with output_folder(out / "cache"):  # a log that cannot be read leaves no empty folder behind
        loaded = load_datasets(out / "cache" / "datasets.npz", key)
        if loaded is None:
            log = read_any(path, formats=("carmen",), max_range=max_range, message=message)
            result = run_planar_benchmark(log, str(path), protocol, tuple(simulators), seed=seed, progress=progress)
            states, ranges = planar_datasets(result, samples=runs, seed=seed)
            benchmark = [r.to_json() for r in result.rows]
            save_datasets(out / "cache" / "datasets.npz", key, _state_arrays(states), ranges, benchmark)
        else:
            arrays, ranges, benchmark = loaded
            states = _states(arrays)
    spent = {"datasets": time.perf_counter() - start, "datasets_cpu": time.process_time() - cpu}
    return evaluate_datasets(
        states, ranges, out, str(path), benchmark, key, draws, runs, seed, workers, progress, spent
    )
