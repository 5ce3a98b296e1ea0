"""Benchmark: fit the hybrid geometric model to about 1M Lidar points; print seconds per stage.

A synthetic world (200 m x 60 m) is ray cast by the true sensor (32 x 1024 rays per scan, a scan
every 3 m: about 2M rays, 1.1-1.3M returns; not timed), then :func:`fit_model` runs ground
segmentation, per-block ground meshes and ellipsoids, and hit probabilities over every ray.
Target: under 120 s on 2 cores.

Usage: ``python bench/bench_fit_scene.py [--spacing 3.0]``
"""

from __future__ import annotations

import argparse
import os
import time

import mi_lidar  # noqa: F401  (selects the Mitsuba variant)
from mi_lidar.hybrid.fit import FitParams, fit_model
from mi_lidar.hybrid.world import SensorSpec, WorldSpec, make_world, path_poses, render_log


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing", type=float, default=3.0, help="metres between scans")
    args = parser.parse_args()
    sensor = SensorSpec(n_firings=1024)
    t0 = time.perf_counter()
    world = make_world(7, WorldSpec(length=200, width=60))
    log = render_log(world, path_poses(world, args.spacing, sensor), sensor, seed=7)
    print(f"world + log: {time.perf_counter() - t0:.1f} s, {len(world.faces)} triangles, "
          f"{log.n_rays} rays, {int(log.hit.sum())} points, cpus={os.cpu_count()}")
    t0 = time.perf_counter()
    result = fit_model(log, FitParams())
    total = time.perf_counter() - t0
    print(f"{'stage':<20}{'seconds':>10}")
    for stage, seconds in result.timings.items():
        print(f"{stage:<20}{seconds:>10.1f}")
    print(f"{'total':<20}{total:>10.1f}")
    print(f"elements: {len(result.model.ground)} triangles, {len(result.model.ellipsoids)} ellipsoids, "
          f"{result.model.info['n_blocks']} blocks; target < 120 s: {'met' if total < 120 else 'NOT met'}")


if __name__ == "__main__":
    main()
