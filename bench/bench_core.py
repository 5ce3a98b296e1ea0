"""Core throughput and memory benchmark (issues 2 and 17).

Measures rays per second of the simulation core against Mitsuba's raw coherent
``scene.ray_intersect`` (the limit of this machine), Open3D's ``RaycastingScene`` and, where
installed, embreex (Embree's Python binding, single-threaded; terrain only) on two scenes built
here:

* **terrain**: a 1M-triangle heightfield, opaque;
* **vegetation**: the same terrain plus 100k Gaussian ellipsoids (shrub and canopy clumps)
  with hit probabilities in [0.2, 0.4] that beams pass through.

Every measurement traces the same ~1M rays (one sweep of a dense 128 x 8192 spinning pattern
2 m above the terrain), excludes a warm-up run (kernel compilation) and reports the fastest of
:data:`REPEATS` rounds in which every method runs once (interleaved, in an order that rotates
every round, so that all share the machine's load; other processes only ever add time, so the
fastest run is the one they disturbed least), with ``dr.sync_thread()`` before each timer read.
Besides raw first-hit casting, the reference of the pass-through path is the minimal
pass-through loop written directly on Mitsuba (:func:`raw_pass_through`: one symbolic loop of
preliminary intersections, a hit-probability lookup and one counter-based draw per element,
the range of the returning element as the result): what ``simulate_rays`` adds on top of it is
the sensor model. Open3D has no ellipsoids: on the vegetation scene it traces each ellipsoid as
an icosahedron (20 triangles at the ellipsoid's extent) and runs the same pass-through loop in
numpy, where exit faces of an icosahedron are crossed without a draw. A peer that is not
installed gets a row saying so, and the targets stated against it are not checked. Peak memory of
a 4M-ray :func:`mi_lidar.simulate` is read from ``VmHWM`` of a child process. The time of
``import mi_lidar`` in a fresh process is set beside that of Mitsuba with its variant alone (the
floor the package cannot go below).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import secrets
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .peers import (
    embreex_first_hit,
    missing_peer,
    open3d_first_hit,
    open3d_pass_through,
    open3d_scene,
    raw_pass_through,
)

CORES = 2  # the targets are set for a 2-core machine
N_BEAMS, N_FIRINGS = 128, 8192  # 1,048,576 rays per sweep
TERRAIN_VERTICES = 708  # per side: 2 * 707^2 = 999,698 triangles
TERRAIN_HALF_SIZE = 125.0  # m; the sensor sits at the centre, max_range is 120 m
N_ELLIPSOIDS = 100_000
ELLIPSOID_EXTENT = 3.0  # sigmas
SENSOR_HEIGHT = 2.0  # m above the terrain
MAX_SEGMENTS = 16
REPEATS = 5
SEED = 7
MEMORY_POSES = 4  # 4 sweeps of 1M rays: the 4M-ray scan
MEMORY_LIMIT_GB = 2.0
IMPORT_LIMIT_S = 0.8  # import mi_lidar in a fresh process
IMPORT_REPEATS = 5
VEGETATION_MRAYS = 10.0  # simulate_rays >= 10 Mrays/s on the vegetation scene
OPEN3D_FACTOR = {"simulate_rays": 2.0, "simulate": 1.5, "render": 1.5}  # terrain: >= this many times Open3D


@dataclass
class Row:
    """One line of the result table.

    Attributes:
        benchmark: what was measured, e.g. ``"terrain: simulate_rays"``.
        mrays: million rays per second (None for memory rows).
        vs_raw: ``mrays`` over raw coherent ``ray_intersect`` on the same scene and rays.
        vs_raw_loop: ``mrays`` over the raw Mitsuba pass-through loop (:func:`raw_pass_through`) on
            the same scene and rays.
        vs_open3d: ``mrays`` over Open3D on the same scene and rays.
        vs_embreex: ``mrays`` over embreex on the same scene and rays (None where not measured).
        target: the target, in words ("" when the row is a reference).
        passed: whether the target is met (None without a target).
        failed: the checks of the target that failed, with their measured values.
        value: text shown instead of ``mrays`` (memory rows).
    """

    benchmark: str
    mrays: float | None = None
    vs_raw: float | None = None
    vs_raw_loop: float | None = None
    vs_open3d: float | None = None
    vs_embreex: float | None = None
    target: str = ""
    passed: bool | None = None
    failed: str = ""
    value: str = ""


# ----------------------------------------------------------------------------------- scenes
def terrain_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Rolling off-road terrain height (m) at (x, y): a few smooth waves."""
    return (
        1.5 * np.sin(0.05 * x) * np.cos(0.04 * y)
        + 0.6 * np.sin(0.13 * x + 0.7)
        + 0.4 * np.cos(0.11 * y - 0.3)
        + 0.15 * np.sin(0.9 * x) * np.sin(0.8 * y)
    )


def make_terrain() -> tuple[np.ndarray, np.ndarray]:
    """The heightfield as (V, 3) vertices and (F, 3) faces, two triangles per grid cell."""
    n = TERRAIN_VERTICES
    axis = np.linspace(-TERRAIN_HALF_SIZE, TERRAIN_HALF_SIZE, n)
    x, y = np.meshgrid(axis, axis, indexing="ij")
    vertices = np.stack([x, y, terrain_height(x, y)], axis=-1).reshape(-1, 3)
    corner = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.concatenate(
        [
            np.stack([corner, corner + n, corner + n + 1], axis=1),
            np.stack([corner, corner + n + 1, corner + 1], axis=1),
        ]
    )
    return vertices, faces


def make_vegetation(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """100k ellipsoids in clumps of 40 over the terrain: half shrubs, half tree canopies.

    Shrub clumps hold ellipsoids of 0.08-0.25 m sigma 0.2-1.5 m above the ground within
    1.5 m of the clump centre; canopies hold 0.15-0.4 m sigmas 3-7 m up within 2.5 m. No clump
    centre lies within 4 m of the sensor.

    Returns:
        Dict of ``centers`` (N, 3), ``scales`` (N, 3) sigmas (m), ``quaternions`` (N, 4)
        (x, y, z, w) and ``p_hit`` (N,) hit probabilities in [0.2, 0.4] (mean 0.3).
    """
    per_clump = 40
    n_clumps = N_ELLIPSOIDS // per_clump
    clump = rng.uniform(-TERRAIN_HALF_SIZE + 3.0, TERRAIN_HALF_SIZE - 3.0, (n_clumps, 2))
    near = np.hypot(clump[:, 0], clump[:, 1]) < 4.0
    clump[near] += 8.0
    tree = np.arange(n_clumps) % 2 == 1
    spread = np.where(tree, 2.5, 1.5)[:, None, None]
    offset = rng.uniform(-1.0, 1.0, (n_clumps, per_clump, 2)) * spread
    xy = (clump[:, None, :] + offset).reshape(-1, 2)
    is_tree = np.repeat(tree, per_clump)
    n = len(xy)
    z = terrain_height(xy[:, 0], xy[:, 1]) + np.where(is_tree, rng.uniform(3.0, 7.0, n), rng.uniform(0.2, 1.5, n))
    low, high = np.where(is_tree, 0.15, 0.08)[:, None], np.where(is_tree, 0.4, 0.25)[:, None]
    scales = low + (high - low) * rng.random((n, 3))
    yaw = rng.uniform(0.0, math.pi, n)
    quaternions = np.stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)], axis=1)
    return {
        "centers": np.column_stack([xy, z]),
        "scales": scales,
        "quaternions": quaternions,
        "p_hit": rng.uniform(0.2, 0.4, n),
    }


def make_pattern():
    """A dense spinning pattern: 128 beams from +2 to -25 degrees, 8192 firings per 0.1 s sweep."""
    from mi_lidar.core.patterns import FiringPattern

    period = 0.1
    elevation = np.radians(np.linspace(2.0, -25.0, N_BEAMS))[:, None].repeat(N_FIRINGS, axis=1)
    time_s = np.arange(N_FIRINGS)[None, :].repeat(N_BEAMS, axis=0) * (period / N_FIRINGS)
    azimuth = math.pi - 2.0 * math.pi * time_s / period
    azimuth = (azimuth + math.pi) % (2.0 * math.pi) - math.pi
    return FiringPattern("bench-128x8192", elevation, azimuth, time_s, period)


def sensor_pose(dx: float = 0.0) -> np.ndarray:
    """Sensor-to-world pose ``dx`` m along x, :data:`SENSOR_HEIGHT` above the terrain."""
    pose = np.eye(4)
    pose[:3, 3] = [dx, 0.0, float(terrain_height(np.array(dx), np.array(0.0))) + SENSOR_HEIGHT]
    return pose


def write_scenes(folder: Path) -> dict[str, Path]:
    """Write the assets and the two scene XMLs (lidar sensor + ``lidar_integrator``).

    Returns:
        ``{"terrain": xml, "vegetation": xml}``.
    """
    from mi_lidar.core.patterns import to_table
    from mi_lidar.scene.files import ShapeEntry, write_ellipsoids_ply, write_mesh_ply, write_scene_xml

    vertices, faces = make_terrain()
    write_mesh_ply(folder / "terrain.ply", vertices, faces)
    veg = make_vegetation(np.random.default_rng(SEED))
    write_ellipsoids_ply(
        folder / "vegetation.ply", veg["centers"], veg["scales"], veg["quaternions"], p_hit=veg["p_hit"]
    )
    pattern = to_table(make_pattern(), folder / "pattern.npy").resolve()  # the sensor reads it from the cwd
    z = sensor_pose()[2, 3]
    sensor = (
        f'    <integrator type="lidar_integrator"><integer name="max_segments" value="{MAX_SEGMENTS}"/>'
        "</integrator>\n"
        f'    <sensor type="lidar"><string name="pattern" value="{pattern}"/>'
        f'<transform name="to_world"><translate z="{z:.9g}"/></transform></sensor>'
    )
    terrain = ShapeEntry(id="terrain", kind="mesh", filename="terrain.ply", label=1)
    vegetation = ShapeEntry(
        id="vegetation", kind="ellipsoids", filename="vegetation.ply", label=2, extent=ELLIPSOID_EXTENT
    )
    return {
        "terrain": write_scene_xml(folder / "terrain.xml", [terrain], "bench: terrain", sensor),
        "vegetation": write_scene_xml(folder / "vegetation.xml", [terrain, vegetation], "bench: vegetation", sensor),
    }


# ----------------------------------------------------------------------------------- timing
def fastest_seconds(runs: dict, repeats: int = REPEATS) -> dict[str, float]:
    """Fastest wall time (s) of each callable in ``runs`` over ``repeats`` rounds, after one warm-up run each.

    Every round runs each callable once, in an order that rotates from round to round, so that they
    share the machine's load. Each callable must evaluate its outputs; Dr.Jit's queue is synchronized
    before each timer read.
    """
    import drjit as dr

    for run in runs.values():
        run()
        dr.sync_thread()
    names = list(runs)
    times = {name: [] for name in names}
    for round_ in range(repeats):
        shift = round_ % len(names)
        for name in names[shift:] + names[:shift]:
            start = time.perf_counter()
            runs[name]()
            dr.sync_thread()
            times[name].append(time.perf_counter() - start)
    return {name: min(values) for name, values in times.items()}


def make_rays(pattern, pose: np.ndarray):
    """The pattern's rays at ``pose`` as a RayBatch, built as :func:`mi_lidar.simulate` does."""
    import drjit as dr
    import mitsuba as mi

    from mi_lidar.core.rays import RayBatch

    height, width = pattern.shape
    d = pattern.directions().reshape(-1, 3).astype(np.float64) @ pose[:3, :3].T
    o = pattern.origins().reshape(-1, 3).astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    return RayBatch(
        origin=mi.Point3f(*o.T.astype(np.float32)),
        direction=dr.normalize(mi.Vector3f(*d.T.astype(np.float32))),
        beam=mi.UInt32(np.repeat(np.arange(height, dtype=np.uint32), width)),
        time=mi.Float(pattern.time.reshape(-1).astype(np.float32)),
        ray_id=dr.arange(mi.UInt32, height * width),
    )


# -------------------------------------------------------------------------------- measuring
def measure_scene(name: str, xml: Path) -> dict[str, float]:
    """Seconds per sweep of every method on one scene, plus statistics of the direct path.

    Returns:
        Dict with ``rays``; the fastest seconds (:func:`fastest_seconds`) of ``raw``, ``raw_loop``,
        ``simulate_rays``, ``simulate``, ``render`` and, when installed, ``open3d`` and (terrain)
        ``embreex``; ``new_seed``, the seconds of one ``simulate_rays`` with a seed never used
        before (kernel compilation included); ``hit_fraction`` / ``mean_segments`` of the direct
        path and ``raw_hit_fraction`` of the raw loop.
    """
    import drjit as dr
    import mitsuba as mi

    import mi_lidar
    from mi_lidar.core.elements import ElementTable
    from mi_lidar.scene.loading import scene_sensor_model

    scene = mi_lidar.load_scene(xml)
    model, pose = scene_sensor_model(scene)
    pattern = make_pattern()
    rays = make_rays(pattern, pose)
    n = dr.width(rays.ray_id)
    table = ElementTable.from_scene(scene)
    ray = mi.Ray3f(rays.origin, rays.direction)
    dr.eval(rays, ray)
    veg = None if name == "terrain" else make_vegetation(np.random.default_rng(SEED))
    p_hit = {"terrain": np.ones(2 * (TERRAIN_VERTICES - 1) ** 2)}  # per shape id: the terrain is opaque
    if veg is not None:
        p_hit["vegetation"] = veg["p_hit"]

    def raw():
        si = scene.ray_intersect(ray, mi.RayFlags.Minimal, True)
        dr.eval(si.t, si.prim_index, si.shape)

    def raw_loop():
        dr.eval(raw_pass_through(scene, p_hit, ray.o, ray.d, rays.ray_id, model.max_range, model.max_segments))

    def direct():
        dr.eval(model.simulate_rays(scene, table, rays, SEED))

    def render():
        dr.eval(mi.render(scene, seed=SEED))

    def end_to_end():
        mi_lidar.simulate(scene, pattern, pose, seed=SEED, model=model)

    runs = {"raw": raw, "raw_loop": raw_loop, "simulate_rays": direct, "simulate": end_to_end, "render": render}
    origin = np.asarray(rays.origin).T.astype(np.float32).copy()
    direction = np.asarray(rays.direction).T.astype(np.float32).copy()
    vertices, faces = make_terrain()
    if not missing_peer("open3d"):
        o3d_scene, per_ellipsoid = open3d_scene(vertices, faces, veg, ELLIPSOID_EXTENT)
        rng = np.random.default_rng(SEED)

        def open3d():
            if veg is None:
                open3d_first_hit(o3d_scene, origin, direction, CORES)
            else:
                open3d_pass_through(
                    o3d_scene, per_ellipsoid, veg["p_hit"], origin, direction, rng, CORES, model.max_range, MAX_SEGMENTS
                )

        runs["open3d"] = open3d
    embree = embreex_first_hit(vertices, faces, origin, direction) if veg is None else None
    if embree is not None:
        runs["embreex"] = embree
    seconds = fastest_seconds(runs)
    fresh_seed = SEED + 1 + secrets.randbelow(1 << 30)  # not in Dr.Jit's kernel cache on disk
    start = time.perf_counter()
    dr.eval(model.simulate_rays(scene, table, rays, fresh_seed))
    dr.sync_thread()
    seconds["new_seed"] = time.perf_counter() - start
    out = model.simulate_rays(scene, table, rays, SEED)
    seconds["hit_fraction"] = float(np.mean(np.asarray(out["hit"])))
    seconds["mean_segments"] = float(np.mean(np.asarray(out["segments"])))
    z = raw_pass_through(scene, p_hit, ray.o, ray.d, rays.ray_id, model.max_range, model.max_segments)
    seconds["raw_hit_fraction"] = float(np.mean(np.isfinite(np.asarray(z))))
    seconds["rays"] = n
    return seconds


def import_seconds(statement: str) -> float:
    """Fastest of :data:`IMPORT_REPEATS` fresh processes timing ``statement``, s."""
    code = f"import time; t = time.perf_counter(); {statement}; print(time.perf_counter() - t)"
    runs = [
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        for _ in range(IMPORT_REPEATS)
    ]
    return min(float(out) for out in runs)


def peak_memory_gb(xml: Path) -> tuple[float, float, int]:
    """Peak resident memory (GB) of a child process simulating a 4M-ray scan of ``xml``.

    Returns:
        ``(peak, baseline, rays)``: VmHWM after the scan, VmHWM after loading the scene and
        the ray count.
    """
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    result = subprocess.run(
        [sys.executable, "-m", "bench.bench_core", "memory", str(xml)],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    if result.returncode != 0:
        raise RuntimeError(f"memory probe failed:\n{result.stderr[-2000:]}")
    report = json.loads(result.stdout.strip().splitlines()[-1])
    return report["peak_gb"], report["baseline_gb"], report["rays"]


def _vm_hwm_gb() -> float:
    """This process's peak resident set size (VmHWM), GB."""
    from mi_lidar.core.resources import peak_resident_mib

    return peak_resident_mib() * 1024**2 / 1e9


def _memory_probe(xml: str) -> None:
    """Child process: simulate a 4M-ray scan of ``xml`` and print peak memory as JSON."""
    pin_cores()
    import mi_lidar

    scene = mi_lidar.load_scene(xml)
    baseline = _vm_hwm_gb()
    pattern = make_pattern()
    poses = np.stack([sensor_pose(dx) for dx in np.linspace(0.0, 3.0, MEMORY_POSES)])
    log = mi_lidar.simulate(scene, pattern, poses, seed=SEED)
    rays = int(np.asarray(log.ranges).size)
    print(json.dumps({"peak_gb": _vm_hwm_gb(), "baseline_gb": baseline, "rays": rays}))


def pin_cores() -> None:
    """Restrict this process to :data:`CORES` CPUs and Dr.Jit to as many threads."""
    if hasattr(os, "sched_getaffinity") and len(os.sched_getaffinity(0)) > CORES:
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:CORES])
    import drjit as dr

    import mi_lidar  # noqa: F401  (configures LLVM before Dr.Jit starts its threads)

    dr.set_thread_count(CORES)


# ---------------------------------------------------------------------------------- results
def _verdict(checks: list[tuple[str, bool]]) -> tuple[bool, str]:
    """Overall pass and the names of the failed checks."""
    failed = [name for name, ok in checks if not ok]
    return not failed, ", ".join(failed)


def run() -> list[Row]:
    """Run every core benchmark and return the table rows."""
    pin_cores()
    rows = []
    with tempfile.TemporaryDirectory(prefix="mi-lidar-bench-") as tmp:
        scenes = write_scenes(Path(tmp))
        for name, xml in scenes.items():
            rows += _scene_rows(name, measure_scene(name, xml))
        peak, baseline, n = peak_memory_gb(scenes["vegetation"])
        rows.append(
            Row(
                f"vegetation: peak memory of mi_lidar.simulate, {n:,} rays",
                target=f"< {MEMORY_LIMIT_GB:g} GB",
                passed=peak < MEMORY_LIMIT_GB,
                failed="" if peak < MEMORY_LIMIT_GB else f"{peak:.2f} GB",
                value=f"{peak:.2f} GB ({baseline:.2f} GB after load)",
            )
        )
    package = import_seconds("import mi_lidar")
    import mitsuba as mi

    floor = import_seconds(f"import mitsuba as mi; mi.set_variant({mi.variant()!r})")
    rows.append(
        Row(
            "import mi_lidar (fresh process, fastest of 5)",
            target=f"< {IMPORT_LIMIT_S:g} s",
            passed=package < IMPORT_LIMIT_S,
            failed="" if package < IMPORT_LIMIT_S else f"{package:.2f} s",
            value=f"{package:.2f} s (Mitsuba and its variant alone {floor:.2f} s)",
        )
    )
    return rows


def _scene_rows(name: str, s: dict) -> list[Row]:
    """The table rows of one scene's measurements (:func:`measure_scene`), with their targets."""
    keys = ("raw", "raw_loop", "simulate_rays", "new_seed", "simulate", "render", "open3d", "embreex")
    mrays = {k: s["rays"] / s[k] / 1e6 for k in keys if k in s}

    def row(label: str, key: str) -> Row:
        rate = mrays[key]
        vs = {peer: rate / mrays[peer] if peer in mrays else None for peer in ("raw", "raw_loop", "open3d", "embreex")}
        checks, target = [], ""
        if name == "terrain" and key in OPEN3D_FACTOR:
            target = f">= {OPEN3D_FACTOR[key]:g}x Open3D"
            if vs["open3d"] is None:
                target += " (not checked: Open3D not installed)"
            else:
                checks = [(f"{vs['open3d']:.2f}x Open3D", vs["open3d"] >= OPEN3D_FACTOR[key])]
        elif name == "vegetation" and key == "simulate_rays":
            checks = [(f"{rate:.1f} Mrays/s", rate >= VEGETATION_MRAYS)]
            target = f">= {VEGETATION_MRAYS:g} Mrays/s"
        passed, failed = _verdict(checks) if checks else (None, "")
        return Row(
            f"{name}: {label}", rate, vs["raw"], vs["raw_loop"], vs["open3d"], vs["embreex"], target, passed, failed
        )

    stats = f"{s['hit_fraction']:.0%} hits, {s['mean_segments']:.2f} elements/ray"
    rows = [
        row("raw ray_intersect (coherent, first hit)", "raw"),
        row(f"raw Mitsuba pass-through loop ({s['raw_hit_fraction']:.0%} hits)", "raw_loop"),
        row(f"simulate_rays ({stats})", "simulate_rays"),
        row("simulate_rays, first call with a new seed", "new_seed"),
        row("mi_lidar.simulate (end to end)", "simulate"),
        row("mi.render (XML, lidar_integrator)", "render"),
    ]
    peers = {"open3d": "Open3D cast_rays" if name == "terrain" else "Open3D icosahedra + numpy pass-through"}
    if name == "terrain":
        peers["embreex"] = "embreex first hit (1 thread)"
    for peer, label in peers.items():
        rows.append(row(label, peer) if peer in mrays else Row(f"{name}: {label}: not run, {missing_peer(peer)}"))
    return rows


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "memory":
    _memory_probe(sys.argv[2])
elif __name__ == "__main__" and sys.argv[1:] == ["rows"]:  # the rows as JSON, for another variant
    print(json.dumps([dataclasses.asdict(row) for row in run()]))
