"""The loop on real data: one Ouster OS-1-32 frame, a scene fitted from part of it (docs/loop_results.md).

Run:  python examples/04_real_ouster.py [OUT]
It decodes ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.pcap and builds a triangle mesh from the
returns of columns 0 mod 4 (the scene); calibration rays are columns 2 mod 4, test rays the odd
columns (nats per ray, 1 cm bins). The loop, as a user runs it:

1. compare the mesh with the test columns (report in OUT/mesh_only/);
2. diagnose which effects are missing, on the calibration columns (OUT/diagnosis/);
3. add effects one by one, fitted on the calibration columns, and print the development path;
4. compare the final model with the test columns (OUT/final/).

OUT defaults to reports/ouster_loop/. About 2 minutes on 2 cores.
"""

import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
from rich.console import Console

import mi_lidar
from mi_lidar.core.effects import make_effect
from mi_lidar.io import read_any
from mi_lidar.loop.compare import compare
from mi_lidar.loop.development import development_table
from mi_lidar.loop.diagnose import diagnose
from mi_lidar.loop.diagnosis_report import verdict
from mi_lidar.loop.real_ouster import MESH_EVERY, column_log, ouster_development_path, range_image_mesh
from mi_lidar.scene.dicts import scene_dict

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "ouster" / "OS-1-32-G_v2.1.1_1024x10.pcap"


def report(name: str, mesh, model, test_log, out: Path, say) -> None:
    """Compare ``model`` in the scene of ``mesh`` with ``test_log`` and write ``out / name``."""
    result = compare(
        test_log,
        mi.load_dict(scene_dict({"map": mesh})),
        model,
        out=out / name,
        title=f"Ouster frame, test columns: {name}",
    )
    head = result.headline
    say(
        f"{name}: NLL {head['nll']:.3f} nats/ray (floored), F1 {head['f1']:.3f}, median |simulated - measured| "
        f"{head['range_error_median']:.3f} m -> {out / name / 'report.html'}"
    )


if __name__ == "__main__":
    console = Console()
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "reports/ouster_loop")
    start = time.perf_counter()
    say = lambda message: console.log(f"[{time.perf_counter() - start:6.1f} s] {message}")  # noqa: E731
    log = read_any(DATA)
    columns = np.arange(log.shape[2])
    test_log = column_log(log, columns[columns % 2 == 1])
    mesh = range_image_mesh(log, columns[columns % MESH_EVERY == 0])

    # 1. compare
    report(
        "mesh_only", mesh, mi_lidar.SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4), test_log, out, say
    )

    # 2. diagnose (the mesh explains no return where no face is on the ray: start with outliers)
    outliers = make_effect("outliers", p_near=0.02, near_scale=2.0, p_uniform=0.005, uniform_max=120.0)
    start_model = mi_lidar.SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4, effects=[outliers])
    found = diagnose(
        column_log(log, columns[columns % MESH_EVERY == MESH_EVERY // 2]),
        mi.load_dict(scene_dict({"map": mesh})),
        start_model,
        out=out / "diagnosis",
    )
    console.print(verdict(found))

    # 3. add effects, watch the error fall
    path = ouster_development_path(log, progress=say)
    console.print(development_table(path.rows, "Ouster OS-1-32 frame, nats per test ray (odd columns, 1 cm bins)"))
    console.print("final model: " + ", ".join(effect.describe() for effect in path.model.effects))  # kept steps only

    # 4. compare again
    report("final", path.mesh, path.model, test_log, out, say)
