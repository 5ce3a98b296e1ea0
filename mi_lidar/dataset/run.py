"""Running a dataset: one Dask task per frame, a manifest that makes every run resumable.

The manifest (``manifest.json``) holds the spec as written, the software versions and, per finished
frame, the SHA-256 of every file it wrote (and the frame's CPU and wall seconds). A new run with the
same spec verifies the recorded frames' digests, keeps the intact ones and renders only the rest;
leftover temporary files of a killed run are removed first. Frames run on a
``distributed.LocalCluster`` (one single-threaded process per core by default) or on an existing
Dask scheduler; each worker imports Mitsuba once, sizes Dr.Jit's thread pool to its share of the
host's cores (:mod:`.workers`), renders one frame at a time and keeps the rig and the current scene
between frames. Dr.Jit's on-disk kernel cache (``~/.drjit``) is shared safely by concurrent
processes: Dr.Jit writes a kernel to a temporary file named by its process id, hard-links it into
place, and checks a checksum when it loads one.
"""

from __future__ import annotations

import json
import os
import platform
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mi_lidar.core.atomic import output_folder
from mi_lidar.core.errors import SpecError
from mi_lidar.core.resources import cpu_seconds, peak_resident_mib
from mi_lidar.core.strict_json import write_json
from mi_lidar.dataset.spec import DatasetSpec

MANIFEST = "manifest.json"
MANIFEST_SAVE_RATIO = 20.0  # throttled manifest writes take at most 1/20 of the run's time (Manifest.save)
WORKER_WAIT_S = 60.0  # how long a run waits for its LocalCluster's workers, or an existing cluster's first
FORMAT = "mi-lidar-dataset"
_WORKER_STATE: dict = {}
_FRAME_LOCK = threading.Lock()  # Dr.Jit's thread pool and the scene cache serve one frame at a time


def software_versions() -> dict[str, str]:
    """Versions of the packages a frame's bytes depend on."""
    from importlib.metadata import version

    versions = {"python": platform.python_version()}
    for package in ("mi-lidar", "mitsuba", "drjit", "numpy", "scipy", "pillow", "matplotlib", "dask", "distributed"):
        try:
            versions[package] = version(package)
        except Exception:
            versions[package] = "absent"
    return versions


def frame_task(spec: DatasetSpec, out: str, index: int) -> dict:
    """Render and write frame ``index`` in this process; returns its manifest record.

    The rig and the current scene are kept in a per-process cache, so a worker loads a scene once for
    all the frames of that scene variant it runs. The record's ``cpu_seconds`` (this process, all
    threads) and ``seconds`` (wall) time the frame, ``scene_seconds`` the scene load it needed (0
    when cached).
    """
    from mi_lidar.dataset.frame import render_frame, write_frame
    from mi_lidar.dataset.rig import build_rig

    with _FRAME_LOCK:
        start, cpu = time.perf_counter(), cpu_seconds()
        if _WORKER_STATE.get("digest") != spec.digest:
            _WORKER_STATE.clear()
            _WORKER_STATE.update(digest=spec.digest, rig=build_rig(spec), scenes={})
        rig = _WORKER_STATE["rig"]
        frame = render_frame(spec, rig, index, _WORKER_STATE["scenes"])
        record = write_frame(Path(out), frame, rig, spec.output.overlays)
        record.update(
            cpu_seconds=round(cpu_seconds() - cpu, 4),
            seconds=round(time.perf_counter() - start, 4),
            scene_seconds=round(frame.scene_seconds, 4),
        )
        return record


def verify_frame(out: Path, record: dict) -> bool:
    """True when every file of a manifest record exists with its recorded SHA-256."""
    from mi_lidar.dataset.frame import file_digest

    return all((out / name).is_file() and file_digest(out / name) == digest for name, digest in record["files"].items())


def remove_partial_files(out: Path) -> int:
    """Delete temporary files left by an interrupted atomic write (``.<stem>.*.tmp<suffix>``); return their count."""
    stale = [p for p in out.rglob(".*") if p.is_file() and ".tmp" in p.name]
    for path in stale:
        path.unlink(missing_ok=True)
    return len(stale)


class Manifest:
    """The run's record on disk: spec, versions, semantic classes and finished frames with digests."""

    def __init__(self, out: Path, data: dict):
        self.out, self.data = out, data
        self.saved_at, self.save_cost = -float("inf"), 0.0

    @classmethod
    def open(cls, out: Path, spec: DatasetSpec, semantic_classes: dict[str, int], notes: list[str]) -> Manifest:
        """The manifest of ``out``: read (same spec required) or started afresh.

        Raises:
            SpecError: ``out`` holds a manifest of a different spec.
        """
        path = out / MANIFEST
        if path.is_file():
            data = json.loads(path.read_text())
            if data.get("format") != FORMAT or data.get("spec_digest") != spec.digest:
                raise SpecError(
                    f"{out} holds a dataset made from a different spec (manifest spec digest "
                    f"{str(data.get('spec_digest'))[:12]}, this spec {spec.digest[:12]}); "
                    "write to a new --out folder, or delete that folder to start over"
                )
            data["versions"] = software_versions()
            return cls(out, data)
        return cls(
            out,
            {
                "format": FORMAT,
                "version": 1,
                "spec": spec.source,
                "spec_digest": spec.digest,
                "frames_total": spec.frames,
                "versions": software_versions(),
                "semantic_classes": {str(i): n for n, i in sorted(semantic_classes.items(), key=lambda kv: kv[1])},
                "notes": notes,
                "frames": {},
                "failed": {},
            },
        )

    @property
    def frames(self) -> dict[str, dict]:
        return self.data["frames"]

    def add(self, record: dict) -> None:
        """Record a finished frame (and forget an earlier failure of it)."""
        self.frames[str(record["frame"])] = record
        self.data["failed"].pop(str(record["frame"]), None)

    def fail(self, index: int, error: str) -> None:
        """Record a frame that failed after its retries."""
        self.data["failed"][str(index)] = error

    def save(self, throttled: bool = False) -> Path | None:
        """Write the manifest atomically; ``throttled``: only if the last write is long enough ago (else None).

        The file grows with the frames, so after each frame it is written only when the time since the
        last write is at least :data:`MANIFEST_SAVE_RATIO` times what that write took: small manifests
        are written after every frame, one of thousands of frames keeps its writes to a few percent of
        the run. A kill loses at most the frames finished since the last write; their files are
        rendered again (atomically) by the next run.
        """
        start = time.monotonic()
        if throttled and start - self.saved_at < MANIFEST_SAVE_RATIO * self.save_cost:
            return None
        path = write_json(self.out / MANIFEST, self.data, sort_keys=True)
        self.saved_at = time.monotonic()
        self.save_cost = self.saved_at - start
        return path


@dataclass
class RunReport:
    """What a run did: frames in the spec, skipped (already done), rendered now, failed (index -> error).

    ``seconds`` is the run's wall time, ``cpu_seconds`` the CPU time of the frames rendered now (their
    worker processes, all threads).
    ``worker_peak_mib`` and ``worker_setup`` (Dr.Jit threads, cores, pid; see
    :func:`~mi_lidar.dataset.workers.worker_setup`) are keyed by Dask worker address.
    """

    total: int
    skipped: int
    rendered: int = 0
    failed: dict[int, str] = field(default_factory=dict)
    removed_partial: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    dashboard: str | None = None
    worker_peak_mib: dict[str, float] = field(default_factory=dict)
    worker_setup: dict[str, dict] = field(default_factory=dict)


def write_poses(out: Path, manifest: Manifest, total: int) -> Path | None:
    """``poses.txt`` (reference camera to world, KITTI 3x4 rows, one per frame) once every frame is done."""
    import numpy as np

    from mi_lidar.io.poses import write_kitti_poses

    if len(manifest.frames) != total:
        return None
    poses = np.array([manifest.frames[str(k)]["reference_camera_to_world"] for k in range(total)])
    return write_kitti_poses(out / "poses.txt", poses)


def run_dataset(
    spec: DatasetSpec,
    out: str | os.PathLike,
    scheduler: str | None = None,
    workers: int | None = None,
    serial: bool = False,
    retries: int = 2,
    dashboard_address: str | None = ":8787",
    progress: Callable[[int, int], None] | None = None,
    announce: Callable[[str], None] = lambda message: None,
) -> RunReport:
    """Render every frame of ``spec`` not already in ``out``'s manifest.

    Raises:
        SpecError: the spec does not fit ``out``'s manifest, a scene is inconsistent with it
            (unknown shape, class or label: found before the first frame by
            :func:`~mi_lidar.dataset.scenes.check_scenes`), or a LocalCluster ``dashboard_address`` has no port
            (:func:`check_dashboard`); other frame errors are retried, then reported.
        SceneError: a scene, annotation or library to render cannot be read.

    Args:
        spec: the dataset spec. out: output folder (on a file system every worker can write).
        scheduler: address of an existing Dask scheduler (``tcp://host:8786``); None starts a LocalCluster.
        workers: LocalCluster processes (default: one per core); each runs Dr.Jit on
            ``cores // workers`` threads (at least 1; on a cluster, cores of its host // workers there).
        serial: render in this process, in frame order, without Dask.
        retries: extra attempts of a failing frame before it is reported.
        dashboard_address: the LocalCluster dashboard's address (None: no dashboard).
        progress: ``progress(done, total)`` after each frame (done counts skipped frames).
        announce: receives one-line messages (dashboard link, cluster size, resume summary).

    Returns:
        The run's report; failed frames are also listed in the manifest.
    """
    from mi_lidar.dataset.frame import INTENSITY_NOTE, semantic_table
    from mi_lidar.dataset.scenes import check_scenes

    out = Path(out)
    if not serial and scheduler is None:
        check_dashboard(dashboard_address)
    start = time.perf_counter()
    with output_folder(out):  # a bad scene leaves no empty folder behind
        report = RunReport(total=spec.frames, skipped=0, removed_partial=remove_partial_files(out))
        manifest = Manifest.open(out, spec, semantic_table(spec), [INTENSITY_NOTE])
        intact = {k: r for k, r in manifest.frames.items() if verify_frame(out, r)}
        manifest.data["frames"] = intact
        todo = [k for k in range(spec.frames) if str(k) not in intact]
        check_scenes(spec, sorted({spec.locate(k)[0] for k in todo}))  # a bad scene fails here, not in every frame
    report.skipped = spec.frames - len(todo)
    if report.skipped or report.removed_partial:
        announce(
            f"resuming: {report.skipped} of {spec.frames} frames verified by digest and kept, "
            f"{report.removed_partial} partial files removed"
        )
    manifest.save()

    def finished(index: int, record: dict | None, error: str | None) -> None:
        if record is not None:
            manifest.add(record)
            report.rendered += 1
            report.cpu_seconds += record["cpu_seconds"]
        else:
            manifest.fail(index, error)
            report.failed[index] = error
        manifest.save(throttled=True)
        if progress is not None:
            progress(report.skipped + report.rendered + len(report.failed), spec.frames)

    if progress is not None:
        progress(report.skipped, spec.frames)
    try:
        if serial:
            for index in todo:
                finished(index, *_attempt(spec, out, index, retries))
        elif todo:
            _run_on_dask(spec, out, todo, scheduler, workers, retries, dashboard_address, finished, announce, report)
    finally:
        manifest.save()
    write_poses(out, manifest, spec.frames)
    report.seconds = time.perf_counter() - start
    return report


def check_dashboard(address: str | None) -> None:
    """Refuse a LocalCluster dashboard address without a port Dask can listen on (``:8787``, ``host:8787``,
    ``8787``; several separated by commas); None or ``""``: no dashboard.

    Raises:
        SpecError: naming the address and what to give (Dask's own error came as a traceback: 'Cluster failed to
            start: invalid literal for int() with base 10').
    """
    if not address:
        return
    for part in address.split(","):
        port = part.rpartition(":")[2]
        if not (port.isdigit() and int(port) <= 65535):
            raise SpecError(
                f"dashboard address {address!r}: {part!r} needs a port number from 0 to 65535 after its last ':', "
                "e.g. ':8787' or 'localhost:8787'; or give '' for no dashboard"
            )


def _attempt(spec: DatasetSpec, out: Path, index: int, retries: int) -> tuple[dict | None, str | None]:
    error = None
    for _ in range(retries + 1):
        try:
            return frame_task(spec, str(out), index), None
        except SpecError:
            raise
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
    return None, error


def _run_on_dask(spec, out, todo, scheduler, workers, retries, dashboard_address, finished, announce, report) -> None:
    from distributed import Client, LocalCluster, as_completed

    from mi_lidar.core.errors import SetupError
    from mi_lidar.dataset.workers import MitsubaWorker, host_cores, worker_setup, workers_per_host

    if scheduler is not None:
        client, cluster = Client(scheduler), None
    else:
        workers = workers or host_cores()
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=dashboard_address
        )
        client = Client(cluster)
    try:
        try:
            # every LocalCluster worker, so that each learns how many share its host's cores (a worker
            # registering late was counted out, and both then ran Dr.Jit on every core); a remote
            # scheduler's workers may come and go: one is enough to start
            client.wait_for_workers(1 if cluster is None else workers, timeout=WORKER_WAIT_S)
        except TimeoutError:
            if cluster is not None:
                raise SetupError(
                    f"the LocalCluster's {workers} workers did not all start within {WORKER_WAIT_S:.0f} s; "
                    "try fewer --workers, or --serial"
                ) from None
            raise SetupError(
                f"the Dask scheduler {scheduler} has had no worker for {WORKER_WAIT_S:.0f} s; "
                f"start some: dask worker {scheduler} --nthreads 1"
            ) from None
        addresses = list(client.scheduler_info(n_workers=-1)["workers"])
        client.register_plugin(MitsubaWorker(workers_per_host(addresses)))
        report.worker_setup = client.run(worker_setup)
        threads = sorted({s["threads"] for s in report.worker_setup.values()})
        # a LocalCluster started without a dashboard address still serves HTTP there, but no dashboard
        services = client.scheduler_info(n_workers=0).get("services", {})
        wanted = scheduler is not None or dashboard_address
        report.dashboard = client.dashboard_link if wanted and "dashboard" in services else None
        announce(
            f"Dask: {len(report.worker_setup)} workers ({'scheduler ' + scheduler if scheduler else 'LocalCluster'}), "
            f"Dr.Jit threads per worker {'/'.join(map(str, threads))}"
            + (f", dashboard {report.dashboard}" if report.dashboard else "")
        )
        futures = {
            client.submit(
                frame_task, spec, str(out), index, key=f"frame-{index}-{spec.digest[:8]}", retries=retries
            ): index
            for index in todo
        }
        for future in as_completed(futures):
            index = futures[future]
            try:
                record = future.result()
            except SpecError:
                client.cancel(list(futures))
                raise
            except Exception as exc:
                finished(index, None, f"{type(exc).__name__}: {exc}")
            else:
                finished(index, record, None)
        report.worker_peak_mib = client.run(peak_resident_mib)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
