"""Benchmark: fit the hybrid geometric model to about 1M Lidar points; print seconds per stage.

A synthetic world (200 m x 60 m) is ray cast by the true sensor (32 x 1024 rays per scan, a scan
every 3 m: about 2M rays, 1.1-1.3M returns; not timed), then :func:`fit_model` runs ground
segmentation, per-block ground meshes and ellipsoids, and hit probabilities over every ray
(counted with the core's multi-element traversal, :func:`mi_lidar.hybrid.simulation.trace_elements`).
Target: under 120 s on 2 cores.

Usage: ``python -m bench.bench_fit_scene [--spacing 3.0]`` (alone) or ``python -m bench`` (every benchmark).
"""

from __future__ import annotations

import argparse
import os
import time

import mi_lidar  # noqa: F401  (selects the Mitsuba variant)
from mi_lidar.hybrid.fit import FitParams, fit_model
from mi_lidar.hybrid.true_sensor import SensorSpec, path_poses, render_log
from mi_lidar.hybrid.world import WorldSpec, make_world

TARGET_S = 120.0


def measure(spacing: float = 3.0) -> dict:
    """Fit the model to the benchmark world's log; return the point count and seconds per stage."""
    sensor = SensorSpec(n_firings=1024)
    start = time.perf_counter()
    world = make_world(7, WorldSpec(length=200, width=60))
    log = render_log(world, path_poses(world, spacing, sensor), sensor, seed=7)
    log_seconds = time.perf_counter() - start
    start = time.perf_counter()
    result = fit_model(log, FitParams())
    return {
        "points": int(log.hit.sum()),
        "rays": log.n_rays,
        "total": time.perf_counter() - start,
        "stages": dict(result.timings),
        "triangles": len(result.model.ground),
        "ellipsoids": len(result.model.ellipsoids),
        "world_triangles": len(world.faces),
        "log_seconds": log_seconds,
        "blocks": result.model.info["n_blocks"],
    }


def run() -> list[dict]:
    """Table rows for ``python -m bench``: total fit time against the target, and each stage."""
    r = measure()
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in r["stages"].items())
    return [
        {
            "benchmark": f"fit-scene: {r['points']:,} points -> {r['triangles']:,} triangles, "
            f"{r['ellipsoids']:,} ellipsoids",
            "value": f"{r['total']:.1f} s",
            "target": f"< {TARGET_S:g} s",
            "passed": r["total"] < TARGET_S,
        },
        {"benchmark": "fit-scene: seconds per stage", "value": stages, "target": "", "passed": None},
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing", type=float, default=3.0, help="metres between scans")
    args = parser.parse_args()
    r = measure(args.spacing)
    print(
        f"{r['world_triangles']} world triangles, {r['rays']} rays, {r['points']} points "
        f"(log {r['log_seconds']:.1f} s, not timed below), cpus={os.cpu_count()}, load {os.getloadavg()[0]:.1f}"
    )
    print(f"fit: {r['triangles']} triangles, {r['ellipsoids']} ellipsoids, {r['blocks']} blocks")
    print(f"{'stage':<20}{'seconds':>10}")
    for stage, seconds in r["stages"].items():
        print(f"{stage:<20}{seconds:>10.1f}")
    print(f"{'total':<20}{r['total']:>10.1f}")
    print(f"target < {TARGET_S:g} s: {'met' if r['total'] < TARGET_S else 'NOT met'}")


if __name__ == "__main__":
    main()
