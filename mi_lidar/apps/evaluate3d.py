"""``mi-lidar evaluate-apps-3d``: 3D scan matching on a real frame and on simulated scans of the same states.

The flow: :func:`~mi_lidar.apps.frames.fit_simulators` fits every simulator on the calibration
columns of the frame; :func:`~mi_lidar.apps.frames.simulated_scans` samples the test columns with
each; the scan-matching application (:class:`~mi_lidar.apps.matching3d.ScanMatching3D`) registers
every scan to the map (the measured calibration points) from the same seeded starts, at the prior
draws and along the development paths (:func:`~mi_lidar.apps.risk.evaluate_application`).

The risk's standard error is over the starts: the starts are resampled with replacement (bootstrap,
:data:`BOOTSTRAP` times, fixed seed), ``J`` is averaged over each resample and the risk recomputed.

Caches (in ``OUT/cache``): ``frame.npz`` (states, scans and the simulators' observation-level rows;
keyed by the capture's SHA-256 and the settings) and ``objectives-<application>.json`` (every
evaluated ``J``), so a rerun, or a run stopped half-way, resumes where it was.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.apps.cache import cache_key, load_datasets, save_datasets
from mi_lidar.apps.frames import SIMULATORS, fit_simulators, frame_states, one_frame, simulated_scans
from mi_lidar.apps.matching3d import FrameStates, ScanMatching3D
from mi_lidar.apps.risk import AppResult, Objectives, evaluate_application
from mi_lidar.core.atomic import output_folder
from mi_lidar.core.params import choose_names

BOOTSTRAP = 400  # resamples of the starts for the risk's standard error


@dataclass
class FrameEvaluation:
    """Result of :func:`evaluate_frame`.

    Attributes:
        source: the capture file.
        states: the shared states (map, test rays, starts).
        simulators: the simulators' names.
        results: one :class:`AppResult` per application.
        risk_se: ``{application: {simulator: standard error of the risk}}``.
        benchmark: per simulator, NLL of the measured test scan and the realism of its sample.
        seconds: time per stage.
    """

    source: str
    states: FrameStates
    simulators: tuple[str, ...]
    results: list[AppResult]
    risk_se: dict
    benchmark: list[dict]
    seconds: dict

    def to_json(self) -> dict:
        return {
            "capture": self.source,
            "map_points": int(len(self.states.map_points)),
            "test_rays": self.states.n,
            "starts": int(len(self.states.starts)),
            "simulators": list(self.simulators),
            "benchmark": self.benchmark,
            "risk_se": self.risk_se,
            "applications": [r.to_json() for r in self.results],
            "seconds": self.seconds,
        }


def risk_standard_error(result: AppResult, seed: int = 0) -> dict[str, float]:
    """Bootstrap standard error of each simulator's risk over the starts (see the module docstring)."""
    per_start = {s: np.array([row["J_starts"] for row in rows]) for s, rows in result.metrics.items()}
    k = per_start["real"].shape[1]
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, k, (BOOTSTRAP, k))
    real = per_start["real"][:, picks].mean(axis=2)  # (draws, BOOTSTRAP)
    return {
        s: float(np.std(np.abs(per_start[s][:, picks].mean(axis=2) - real).mean(axis=0), ddof=1)) for s in result.risk
    }


FRAME_ARRAYS = ("map_points", "origins", "directions", "starts")  # the cached fields of FrameStates, in order


def _key(path: Path, simulators, starts: int, seed: int, steps: int) -> str:
    return cache_key(path, {"sim": list(simulators), "starts": starts, "seed": seed, "steps": steps})


def frame_datasets(log, simulators=SIMULATORS, starts: int = 8, seed: int = 0, steps: int = 1500, progress=None):
    """States, scans and observation-level rows of one frame (no cache): see :mod:`mi_lidar.apps.frames`."""
    say = progress or (lambda message: None)
    frame = one_frame(log)
    mesh, models = fit_simulators(frame, simulators, steps=steps, progress=say)
    ranges, benchmark = simulated_scans(frame, mesh, models, seed)
    return frame_states(frame, starts, seed), ranges, benchmark


def evaluate_frame(
    path: str | Path,
    out: str | Path,
    simulators: tuple[str, ...] = SIMULATORS,
    draws: int = 16,
    starts: int = 8,
    seed: int = 0,
    steps: int = 1500,
    progress=None,
) -> FrameEvaluation:
    """Fit, simulate and evaluate the 3D applications on one frame of a capture; write the report to ``out``.

    Args:
        path: an Ouster or Velodyne capture (pcap) or any log :func:`~mi_lidar.io.read_any` reads;
            its scan with the most returns is the frame.
        out: report folder (``apps3d.json``, ``apps3d.html``, PNGs, ``cache/``).
        simulators: names from :data:`~mi_lidar.apps.frames.SIMULATORS`.
        draws: prior draws of the risk.
        starts: seeded initial-pose errors per registration.
        seed: seed of the sampled scans, the starts and the draws.
        steps: Adam steps per fit of the mi-lidar development path.
        progress: optional ``progress(done, total, label)``.
    """
    from mi_lidar.apps.report3d import write_report
    from mi_lidar.io import read_any

    simulators = choose_names(simulators, SIMULATORS, "evaluate-apps-3d: unknown simulators")
    path, out = Path(path), Path(out)
    say = progress or (lambda done, total, label: None)
    start = time.perf_counter()
    key = _key(path, simulators, starts, seed, steps)
    with output_folder(out / "cache"):  # a frame that cannot be read leaves no empty folder behind
        loaded = load_datasets(out / "cache" / "frame.npz", key)
        if loaded is None:
            say(0, 1, f"reading {path.name}")
            states, ranges, benchmark = frame_datasets(
                read_any(path), tuple(simulators), starts, seed, steps, lambda message: say(0, 1, message)
            )
            save_datasets(
                out / "cache" / "frame.npz", key, {k: getattr(states, k) for k in FRAME_ARRAYS}, ranges, benchmark
            )
        else:
            arrays, ranges, benchmark = loaded
            states = FrameStates(*(arrays[k] for k in FRAME_ARRAYS))
    seconds = {"datasets": time.perf_counter() - start}
    app = ScanMatching3D()
    done = [0]
    hint = (draws + 60) * len(ranges)

    def tick(label: str) -> None:
        done[0] += 1
        say(min(done[0], hint), hint, f"evaluating {label}")

    objectives = Objectives(states, ranges, out / "cache" / f"objectives-{app.name}.json", f"{key}|{draws}", tick)
    result = evaluate_application(app, objectives, m=draws, seed=seed)
    seconds["applications"] = time.perf_counter() - start - seconds["datasets"]
    seconds["total"] = time.perf_counter() - start
    evaluation = FrameEvaluation(
        str(path),
        states,
        tuple(name for name in ranges if name != "real"),
        [result],
        {app.name: risk_standard_error(result, seed)},
        benchmark,
        seconds,
    )
    write_report(evaluation, out)
    return evaluation
