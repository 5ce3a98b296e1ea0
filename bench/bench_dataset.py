"""Dataset scaling benchmark (issue 15): frames per minute on a LocalCluster of 1 and 2 workers.

A 24-frame spec (12 frames of the urban street, 12 of the bundled off-road scene; one VLP-16 with
the scene's 2 cm range noise, two 320 x 180 cameras at 8 samples per pixel, no overlays) is rendered
once per cluster size into a temporary folder. Throughput is steady state: frames finished after
each worker's warm-up (the first ``workers`` completions) over the time they took. Each worker runs
Dr.Jit on ``cores // workers`` threads. Peak memory is each worker process's ``ru_maxrss``.
Target: 2 workers reach >= 1.6x the frames per minute of 1 worker on this 2-core machine.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

SCENES = Path(__file__).resolve().parents[1] / "scenes_xml"
FRAMES_PER_SCENE = 12
TARGET_RATIO = 1.6
SPEC = """
name: bench
seed: 1
rig:
  lidars: [{{name: top, pattern: vlp16, mount: {{xyz: [0, 0, 1.8]}}}}]
  cameras:
    - {{name: front, width: 320, height: 180, fov_deg: 80, mount: {{xyz: [0.5, 0, 1.6]}}}}
    - {{name: left, width: 320, height: 180, fov_deg: 80, mount: {{xyz: [0, 0.3, 1.6], rpy_deg: [0, 0, 90]}}}}
scenes:
  - name: street
    xml: {street}
    frames: {frames}
    labels: {{1: road, 2: building, 3: pole, 4: car, 6: vegetation}}
    objects: [{{class: Car, shapes: [car_body, car_cabin]}}]
    trajectory: {{waypoints: [[-15, 0], [15, 0]]}}
  - name: offroad
    xml: {offroad}
    frames: {frames}
    labels: {{1: ground, 5: small_shrub, 6: medium_shrub}}
    trajectory: {{waypoints: [[-20, 0, 0.2], [20, 0, 0.2]]}}
output: {{spp: 8}}
"""


def throughput(spec, workers: int) -> tuple[float, dict]:
    """Steady-state frames per minute and peak MiB per worker of one LocalCluster run."""
    from mi_lidar.dataset import run_dataset

    done_at: list[float] = []
    with tempfile.TemporaryDirectory() as out:
        report = run_dataset(
            spec,
            out,
            workers=workers,
            dashboard_address=None,
            progress=lambda done, total: done_at.append(time.perf_counter()) if done else None,
        )
    if report.failed:
        raise RuntimeError(f"benchmark frames failed: {report.failed}")
    steady = done_at[workers - 1 :]
    return 60 * (len(steady) - 1) / (steady[-1] - steady[0]), report.worker_peak_mib


def run() -> list[dict]:
    """Render the spec on 1 and 2 workers; return the table rows."""
    from mi_lidar.dataset import load_spec

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bench.yaml"
        path.write_text(
            SPEC.format(street=SCENES / "urban_street.xml", offroad=SCENES / "offroad.xml", frames=FRAMES_PER_SCENE)
        )
        spec = load_spec(path)
        one, memory_one = throughput(spec, 1)
        two, memory_two = throughput(spec, 2)
    ratio = two / one
    memory = ", ".join(f"{v:.0f}" for v in list(memory_one.values()) + list(memory_two.values()))
    return [
        {"benchmark": f"dataset: {spec.frames} frames, 1 worker (frames/min)", "value": f"{one:.1f}"},
        {
            "benchmark": f"dataset: {spec.frames} frames, 2 workers (frames/min; peak MiB per worker, 1 then 2)",
            "value": f"{two:.1f} ({ratio:.2f}x); {memory}",
            "target": f">= {TARGET_RATIO}x 1 worker",
            "passed": ratio >= TARGET_RATIO,
            "failed": "" if ratio >= TARGET_RATIO else f"{ratio:.2f}x",
        },
    ]
