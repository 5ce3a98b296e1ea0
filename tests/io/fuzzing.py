"""Seeded mutation fuzzing of every reader, each mutant read in a worker process with a time limit.

A *seed* is a small valid file of one format (built by :func:`build_seeds`); a *mutant* is the
seed damaged by one to three seeded mutations (bit flips, truncation, byte insertion or deletion,
a header field overwritten with an extreme value, a number token of a text format replaced by an
extreme one, a chunk duplicated). Every mutant must either read or raise the reader's documented
error type with a message naming the file; anything else is a *traceback*, a worker that dies is a
*crash*, and a read that takes longer than the limit is a *hang* (the worker is killed and
restarted). The limit detects hangs; it is not a speed requirement.
"""

from __future__ import annotations

import gzip
import json
import multiprocessing
import re
import shutil
import tempfile
import threading
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError, ParameterError, PatternError, PoseError, SceneError

HANG_SECONDS = 5.0
WARMUP_SECONDS = 300.0
OUTCOMES = ("read", "error", "unnamed", "traceback", "crash", "hang")


@dataclass(frozen=True)
class Reader:
    """How to read one seed: the file to damage, the reader and the error type it documents.

    Attributes:
        seed: File name of the seed in the seed folder.
        read: ``read(mutant, folder)`` reads the damaged copy ``mutant`` (companion files, e.g.
            the capture of a metadata JSON, come from the seed folder ``folder``).
        errors: The exception types the reader documents for bad input.
        names: Companion file names an error message may name instead of the mutant's.
        bag: The seed is a file inside a ROS 2 bag folder; the mutant is read as a bag folder.
    """

    seed: str
    read: Callable[[Path, Path], object]
    errors: tuple = (LogFormatError,)
    names: tuple[str, ...] = ()
    bag: bool = False


def _io():
    import mi_lidar.io as io

    return io


def _load_npz(mutant: Path, folder: Path):
    from mi_lidar.core.log import Log

    return Log.load(mutant)


def _load_density(mutant: Path, folder: Path):
    from mi_lidar.core.densities.tables import load_density

    return load_density(mutant)


def _load_pattern(mutant: Path, folder: Path):
    from mi_lidar.core.patterns import from_table

    return from_table(mutant)


def _load_annotation(mutant: Path, folder: Path):
    from mi_lidar.hybrid.compose import annotation_sensor, load_annotation

    return load_annotation(mutant), annotation_sensor(mutant)


def _load_library(mutant: Path, folder: Path):
    from mi_lidar.hybrid.primitives import PrimitiveLibrary

    return PrimitiveLibrary.load(mutant.parent)


def _load_scene(mutant: Path, folder: Path):
    from mi_lidar.scene import load_scene

    return load_scene(mutant)


DENSITY_FAMILIES = ("np-reg", "p-reg", "beam")  # the learned families and a parametric one, as fit-sensor saves them
OUSTER_PROFILES = {
    "ouster-legacy": "LEGACY",
    "ouster-rng19": "RNG19_RFL8_SIG16_NIR16",
    "ouster-rng19-dual": "RNG19_RFL8_SIG16_NIR16_DUAL",
    "ouster-rng15": "RNG15_RFL8_NIR8",
}

READ_ANY_SEEDS = {
    "npz": "log.npz",
    "kitti-bin": "k.bin",
    "ply": "s.ply",
    "pcd": "s.pcd",
    "las": "s.las",
    "exr": "s.exr",
}
READERS: dict[str, Reader] = {
    "carmen": Reader("c.log", lambda m, f: _io().read_carmen(m)),
    "carmen-gz": Reader("c.log.gz", lambda m, f: _io().read_carmen(m)),
    "npz": Reader("log.npz", _load_npz),
    **{
        name: Reader(f"{name}.pcap", lambda m, f, n=name: _io().read_ouster(m, metadata=f / f"{n}.json"), names=())
        for name in OUSTER_PROFILES
    },
    "ouster-json": Reader(
        "ouster-legacy.json", lambda m, f: _io().read_ouster(f / "ouster-legacy.pcap", metadata=m), names=("pcap",)
    ),
    "velodyne-pcap": Reader("v.pcap", lambda m, f: _io().read_velodyne(m)),
    "velodyne-yaml": Reader("v.yaml", lambda m, f: _io().read_velodyne(f / "v.pcap", calibration=m), names=("v.pcap",)),
    "kitti-bin": Reader("k.bin", lambda m, f: _io().read_bin_log(m)),
    "nuscenes-bin": Reader("n.pcd.bin", lambda m, f: _io().read_bin_log(m)),
    "ply": Reader("s.ply", lambda m, f: _io().read_ply_log(m)),
    "pcd": Reader("s.pcd", lambda m, f: _io().read_pcd_log(m)),
    "pcd-ascii": Reader("a.pcd", lambda m, f: _io().read_pcd_log(m)),
    "las": Reader("s.las", lambda m, f: _io().read_las_log(m)),
    "exr": Reader("s.exr", lambda m, f: _io().read_exr_log(m)),
    **{  # the dispatch users and commands go through: signature and value checks before and after the reader
        f"read-any-{name}": Reader(seed, lambda m, f: _io().read_any(m), (LogFormatError, PoseError))
        for name, seed in READ_ANY_SEEDS.items()
    },
    "rosbag2-db3": Reader("bag/bag.db3", lambda m, f: _io().read_rosbag_log(m.parent), bag=True),
    "rosbag2-yaml": Reader("bag/metadata.yaml", lambda m, f: _io().read_rosbag_log(m.parent), bag=True),
    "poses-kitti": Reader("poses.txt", lambda m, f: _io().read_kitti_poses(m), (LogFormatError, PoseError)),
    "poses-npy": Reader("poses.npy", lambda m, f: _io().read_pose_matrices(m), (LogFormatError, PoseError)),
    "poses-matrix": Reader("matrices.txt", lambda m, f: _io().read_pose_matrices(m), (LogFormatError, PoseError)),
    "poses-any-text": Reader("poses.txt", lambda m, f: _io().read_poses(m), (LogFormatError, PoseError)),
    "poses-any-npy": Reader("poses.npy", lambda m, f: _io().read_poses(m), (LogFormatError, PoseError)),
    "scene-xml": Reader("scene.xml", _load_scene, (SceneError,)),
    **{
        f"density-{family}": Reader(f"{family}.npz", _load_density, (LogFormatError, ParameterError))
        for family in DENSITY_FAMILIES
    },
    "pattern-npy": Reader("pattern.npy", _load_pattern, (PatternError,)),
    "pattern-csv": Reader("pattern.csv", _load_pattern, (PatternError,)),
    "annotation": Reader("annotation.json", _load_annotation, (SceneError,)),
    "library-index": Reader("lib/library.json", _load_library, (SceneError,), bag=True),
    "library-primitive": Reader("lib/rock.npz", _load_library, (SceneError,), bag=True),
}

SCENE_XML = """<?xml version="1.0" encoding="utf-8"?>
<scene version="3.0.0">
    <integrator type="lidar_integrator"><integer name="max_segments" value="4"/></integrator>
    <sensor type="lidar">
        <string name="pattern" value="planar-360"/>
        <float name="max_range" value="30"/>
        <transform name="to_world"><translate x="0" y="0" z="0.5"/></transform>
    </sensor>
    <shape type="cube" id="wall">
        <transform name="to_world"><scale x="0.05" y="3" z="1.5"/><translate x="5" y="0" z="1.5"/></transform>
        <bsdf type="lidar_material"><integer name="label" value="1"/><float name="range_sigma" value="0.01"/></bsdf>
    </shape>
    <shape type="sphere" id="ball">
        <point name="center" x="-2" y="1" z="0.5"/><float name="radius" value="0.3"/>
        <bsdf type="lidar_material"><integer name="label" value="2"/></bsdf>
    </shape>
</scene>
"""


def build_seeds(folder: Path) -> Path:
    """Write one valid seed file per reader of :data:`READERS` into ``folder`` and return it."""
    from mi_lidar.io import write_any, write_kitti_poses, write_pcd

    from .synth import carmen_text, pcap_bytes, velodyne_payloads, write_ouster
    from .test_clouds import synthetic_log

    rng = np.random.default_rng(0)
    for name, profile in OUSTER_PROFILES.items():
        pcap = write_ouster(folder, rng.integers(0, 90000, (8, 32)).astype(np.uint32), profile=profile)
        pcap.rename(folder / f"{name}.pcap")
        pcap.with_suffix(".json").rename(folder / f"{name}.json")
    azimuth = np.arange(36).reshape(3, 12) * 40.0
    distances = rng.integers(0, 3000, (3, 12, 32))
    (folder / "v.pcap").write_bytes(pcap_bytes(velodyne_payloads(distances, azimuth), 2368, step=1327.104e-6))
    (folder / "v.yaml").write_text(
        "lasers:\n"
        + "".join(
            f"- {{laser_id: {i}, rot_correction: 0.0, vert_correction: {np.radians(2 * i - 15):.6f}}}\n"
            for i in range(16)
        )
    )
    (folder / "c.log").write_text(carmen_text(3))
    (folder / "c.log.gz").write_bytes(gzip.compress(carmen_text(3).encode()))
    log = synthetic_log(height=4, width=16)
    synthetic_log(height=4, width=16, scans=2).save(folder / "log.npz")
    nuscenes = np.concatenate([rng.normal(size=(64, 4)), np.tile(np.arange(4), 16)[:, None]], 1)
    nuscenes.astype("<f4").tofile(folder / "n.pcd.bin")
    write_any(log, folder / "k.bin")
    for suffix in (".ply", ".pcd", ".las", ".exr"):
        write_any(log, folder / f"s{suffix}")
    write_pcd(folder / "a.pcd", {c: np.arange(20, dtype=np.float32) + i for i, c in enumerate("xyz")}, binary=False)
    write_any(log, folder / "bag")
    angles = np.linspace(0, 2, 4)
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 0] = poses[:, 1, 1] = np.cos(angles)
    poses[:, 0, 1], poses[:, 1, 0] = -np.sin(angles), np.sin(angles)
    poses[:, :3, 3] = rng.normal(size=(4, 3))
    write_kitti_poses(folder / "poses.txt", poses)
    np.save(folder / "poses.npy", poses)
    np.savetxt(folder / "matrices.txt", poses.reshape(4, 16))
    (folder / "scene.xml").write_text(SCENE_XML)
    _write_model_seeds(folder)
    missing = [name for name, reader in READERS.items() if not (folder / reader.seed).is_file()]
    assert not missing, f"seeds not built: {missing}"
    return folder


def _write_model_seeds(folder: Path) -> None:
    """Seeds of the files a user feeds the models: fitted densities, pattern tables, an annotation, a library."""
    import mi_lidar
    from mi_lidar.core.patterns import get_pattern, to_table
    from mi_lidar.hybrid.compose import save_annotation
    from mi_lidar.loop.sensor_fit import fit_sensor
    from mi_lidar.scene import load_scene
    from mi_lidar.scene.files import write_mesh_ply
    from tests.conftest import SCENES
    from tests.hybrid.libraries import small_library

    scene = load_scene(SCENES / "indoor_planar.xml")
    log = mi_lidar.simulate(scene, seed=1)
    for family in DENSITY_FAMILIES:
        fit_sensor(log, scene, family, steps=20).model.density.save(folder / f"{family}.npz")
    pattern = get_pattern("vlp16", n_firings=8)
    to_table(pattern, folder / "pattern.npy")
    to_table(pattern, folder / "pattern.csv")
    write_mesh_ply(folder / "ground.ply", np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0.0]]), np.array([[0, 1, 2]]))
    objects = [{"class": "small_tree", "center": [1.0, 1.0, 1.5], "yaw": 0.3, "extents": [1.0, 1.2, 3.0]}]
    (annotation,) = save_annotation(folder / "annotation.json", objects)
    doc = json.loads(annotation.read_text())
    doc["ground"] = "ground.ply"
    doc["sensor"] = {"pattern": "vlp16", "poses": [np.eye(4).ravel().tolist()], "min_range": 1.0, "max_range": 80.0}
    annotation.write_text(json.dumps(doc))
    small_library(folder / "lib")


_EXTREMES = (0, 1, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 2**63 - 1, 2**64 - 1)
_TEXT_EXTREMES = ("0", "-1", "nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "99999999999999999999", "", "x")
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One to three seeded mutations of ``data`` (see the module docstring)."""
    out = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        kind = rng.choice(["flip", "truncate", "insert", "delete", "field", "number", "duplicate"])
        size = len(out)
        if size == 0:
            break
        at = int(rng.integers(0, size))
        if kind == "flip":
            for position in rng.integers(0, size, int(rng.integers(1, 9))):
                out[position] ^= 1 << int(rng.integers(0, 8))
        elif kind == "truncate":
            del out[at:]
        elif kind == "insert":
            out[at:at] = rng.integers(0, 256, int(rng.integers(1, 65)), dtype=np.uint8).tobytes()
        elif kind == "delete":
            del out[at : at + int(rng.integers(1, 65))]
        elif kind == "field":
            width = int(rng.choice([1, 2, 4, 8]))
            start = int(rng.integers(0, max(min(size, 512) - width, 1)))
            value = int(rng.choice(_EXTREMES)) & ((1 << (8 * width)) - 1)
            out[start : start + width] = value.to_bytes(width, str(rng.choice(["little", "big"])))
        elif kind == "number":
            numbers = list(_NUMBER.finditer(bytes(out)))
            if numbers:
                match = numbers[int(rng.integers(0, len(numbers)))]
                out[match.start() : match.end()] = str(rng.choice(_TEXT_EXTREMES)).encode()
        else:
            length = int(rng.integers(1, 257))
            out[at:at] = out[at : at + length]
    return bytes(out)


def _quiet_and_bounded() -> None:
    """Worker setup: a capped data segment (a mutant claiming terabytes fails with MemoryError) and
    stdout and stderr to /dev/null (libraries print warnings about every damaged file)."""
    import os
    import resource

    limit = 6 * 1024**3
    resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)


def _serve(conn) -> None:
    """Worker loop: read ``(reader, mutant, seed folder)`` jobs and send back ``(outcome, detail)``."""
    _quiet_and_bounded()
    while True:
        job = conn.recv()
        if job is None:
            return
        name, mutant, folder = job
        reader = READERS[name]
        mutant, folder = Path(mutant), Path(folder)
        try:
            reader.read(mutant, folder)
        except reader.errors as exc:
            message = str(exc)
            named = any(n in message for n in (mutant.name, mutant.parent.name, *reader.names))
            conn.send(("error" if named else "unnamed", f"{type(exc).__name__}: {message}"))
        except BaseException:
            conn.send(("traceback", traceback.format_exc()))
        else:
            conn.send(("read", ""))


class Worker:
    """One reader process; restarted after a hang or a crash."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.context = multiprocessing.get_context("spawn")
        self.process = None
        self.conn = None

    def _start(self) -> None:
        self.conn, child = self.context.Pipe()
        self.process = self.context.Process(target=_serve, args=(child,), daemon=True)
        self.process.start()
        child.close()
        for name, reader in READERS.items():  # imports and first-call work, outside the hang limit
            outcome, detail = self._ask(name, self.folder / reader.seed, WARMUP_SECONDS)
            assert outcome == "read", f"the {name} seed does not read cleanly: {outcome} {detail}"

    def _ask(self, name: str, path: Path, timeout: float) -> tuple[str, str]:
        self.conn.send((name, str(path), str(self.folder)))
        if not self.conn.poll(timeout):
            self.stop()
            return "hang", f"no answer within {timeout:.0f} s"
        try:
            return self.conn.recv()
        except EOFError:
            code = self.process.exitcode if self.process else None
            self.stop()
            return "crash", f"worker died (exit code {code})"

    def read(self, name: str, path: Path) -> tuple[str, str]:
        """Read ``path`` with reader ``name``: ``(outcome, detail)``, outcome one of :data:`OUTCOMES`."""
        if self.process is None:
            self._start()
        return self._ask(name, path, HANG_SECONDS)

    def stop(self) -> None:
        if self.process is not None:
            if self.process.is_alive():
                self.process.kill()
            self.process.join()
            self.conn.close()
        self.process = self.conn = None


@dataclass
class Tally:
    """Outcomes of the mutants of one reader, with the first example of each failure kind."""

    counts: Counter = field(default_factory=Counter)
    examples: dict = field(default_factory=dict)

    @property
    def failures(self) -> int:
        return sum(self.counts[k] for k in ("unnamed", "traceback", "crash", "hang"))


def write_mutant(folder: Path, reader: Reader, data: bytes, scratch: Path) -> Path:
    """Place a mutant's bytes where ``reader`` expects them (a copied bag folder for bags)."""
    if reader.bag:
        bag = scratch / "bag"
        shutil.copytree(folder / Path(reader.seed).parent, bag)
        target = bag / Path(reader.seed).name
    else:
        target = scratch / Path(reader.seed).name
    target.write_bytes(data)
    return target


def fuzz(workers: list[Worker], names: list[str], count: int, seed: int) -> dict[str, Tally]:
    """Read ``count`` mutants of each reader in ``names``, spread over ``workers`` (threads).

    Mutant ``i`` of reader ``name`` is derived from ``(seed, name, i)`` alone, so a failure
    reproduces with :func:`mutant_bytes`.
    """
    folder = workers[0].folder
    jobs = [(name, i) for name in names for i in range(count)]
    tallies = {name: Tally() for name in names}
    lock = threading.Lock()

    def run(worker: Worker) -> None:
        while True:
            with lock:
                if not jobs:
                    return
                name, index = jobs.pop()
            reader = READERS[name]
            data = mutant_bytes(folder, name, seed, index)
            with tempfile.TemporaryDirectory(prefix=f"fuzz-{name}-") as scratch:
                outcome, detail = worker.read(name, write_mutant(folder, reader, data, Path(scratch)))
            with lock:
                tallies[name].counts[outcome] += 1
                tallies[name].examples.setdefault(outcome, f"mutant {index}: {detail}")

    threads = [threading.Thread(target=run, args=(w,)) for w in workers]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return tallies


def mutant_bytes(folder: Path, name: str, seed: int, index: int) -> bytes:
    """The bytes of mutant ``index`` of reader ``name`` (deterministic)."""
    key = [seed, index, *json.dumps(name).encode()]
    return mutate((folder / READERS[name].seed).read_bytes(), np.random.default_rng(key))


def table(tallies: dict[str, Tally]) -> str:
    """A plain-text table: reader, mutants, read, errors, unnamed, tracebacks, crashes, hangs."""
    header = f"{'reader':<18}{'mutants':>8}{'read':>7}{'errors':>8}{'unnamed':>9}{'tracebacks':>11}"
    header += f"{'crashes':>8}{'hangs':>7}"
    rows = [header, "-" * len(header)]
    for name, tally in tallies.items():
        c = tally.counts
        rows.append(
            f"{name:<18}{sum(c.values()):>8}{c['read']:>7}{c['error']:>8}{c['unnamed']:>9}"
            f"{c['traceback']:>11}{c['crash']:>8}{c['hang']:>7}"
        )
    return "\n".join(rows)


def failure_report(tallies: dict[str, Tally]) -> str:
    """The first example of every failure kind, per reader."""
    lines = []
    for name, tally in tallies.items():
        for outcome in ("unnamed", "traceback", "crash", "hang"):
            if outcome in tally.examples:
                lines.append(f"--- {name} {outcome} ({tally.counts[outcome]}x): {tally.examples[outcome]}")
    return "\n".join(lines)
