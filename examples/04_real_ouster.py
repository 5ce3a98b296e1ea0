"""The loop on real data: one Ouster OS-1-32 frame, a scene fitted from part of it (docs/loop_results.md).

Run:  python examples/04_real_ouster.py [OUT]
It decodes ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.pcap, builds a triangle mesh from the
returns of columns 0 mod 4, fits effects (and per-face hit probabilities) on columns 2 mod 4, and
prints the development path in nats per test ray (odd columns, 1 cm bins). It then compares the
first and the final model with the test columns and writes both reports (PNG plots, residual
range image, report.md / report.html) to OUT (default: ouster_loop/). About a minute on 2 cores.
"""

import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
from rich.console import Console
from rich.table import Table

import mi_lidar
from mi_lidar.calibration.scene_dicts import scene_dict
from mi_lidar.io import read_any
from mi_lidar.loop.compare import compare
from mi_lidar.loop.real_ouster import MESH_EVERY, column_log, ouster_development_path, range_image_mesh

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap"

if __name__ == "__main__":
    console = Console()
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "ouster_loop")
    start = time.perf_counter()
    say = lambda message: console.log(f"[{time.perf_counter() - start:6.1f} s] {message}")  # noqa: E731
    log = read_any(DATA)
    path = ouster_development_path(log, progress=say)
    table = Table(title="Ouster OS-1-32 frame, nats per test ray (odd columns, 1 cm bins)")
    for column in ("model", "added", "test NLL", "calibration NLL", "new parameters"):
        table.add_column(column)
    previous = {}
    for row in path.rows:
        fitted = ", ".join(f"{k}={v:.4g}" for k, v in row.fitted.items() if k not in previous)
        table.add_row(row.model, row.added, f"{row.nll:.3f}", f"{row.train_nll:.3f}", fitted)
        previous = row.fitted
    console.print(table)
    console.print("final parameters: " + ", ".join(f"{k}={v:.4g}" for k, v in previous.items()))

    columns = np.arange(log.shape[2])
    test_log = column_log(log, columns[columns % 2 == 1])
    first = range_image_mesh(log, columns[columns % MESH_EVERY == 0])
    for name, mesh, model in (("mesh_only", first, mi_lidar.SensorModel(range_sigma=0.01, max_range=120.0,
                                                                         max_segments=4)),
                              ("final", path.mesh, path.model)):
        scene = mi.load_dict(scene_dict({"map": mesh}))
        result = compare(test_log, scene, model, out=out / name, title=f"Ouster frame, test columns: {name}")
        head = result.headline
        say(f"{name}: NLL {head['nll']:.3f} nats/ray, F1 {head['f1']:.3f}, median |range error| "
            f"{head['range_error_median']:.3f} m -> {out / name / 'report.html'}")
