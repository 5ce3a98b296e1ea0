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

import argparse
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
from rich.console import Console, Group
from rich.text import Text

import mi_lidar
from mi_lidar.cli.app import say as print_verdict
from mi_lidar.cli.tables import figure, figure_table
from mi_lidar.core.effects import make_effect
from mi_lidar.io import read_any
from mi_lidar.loop.compare import compare
from mi_lidar.loop.development import Step
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


def path_tables(rows: list[Step], title: str) -> Group:
    """The development path as two tables that read whole at 80 columns, and why a step was not kept.

    The first table has a row per step, named by the effect it adds (``+ corner_returns``; the law or
    the faces it acts on go in the caption), beside its test and calibration NLL and the realism of its
    samples; the second the parameters each step adds, with their fitted values.
    """
    figures, parameters, notes, details = [], [], [], []
    kept: dict = {}
    for row in rows:
        effect = row.added.removeprefix("+ ")  # "+ label_dropout (faces closing holes)", or "(mesh only)"
        name = effect.partition(" (")[0]
        not_kept = " (not kept)" if row.rejected else ""
        label = "mesh only" if effect == "(mesh only)" else f"+ {name}{not_kept}"
        if name != effect:
            details.append(effect)
        if row.rejected:
            notes.append(Text(f"{name} not kept: {row.rejected}"))  # as written: a [...] would be read as markup
        s = row.samples
        realism = [figure(s.get(k, float("nan"))) for k in ("range_error_median", "histogram_l1", "f1")]
        figures.append((label, figure(row.nll), figure(row.train_nll), *realism))
        parameters += [(k + not_kept, f"{v:.4g}") for k, v in row.fitted.items() if k not in kept]
        kept = kept if row.rejected else row.fitted
    steps = figure_table(
        title,
        "step",
        ("test\nNLL", "calib.\nNLL", "sample\n|err|", "hist\nL1", "F1"),
        caption="NLL: nats per beam on the test and the calibration beams. One scan sampled at the test beams: "
        "sample |err| median |measured - sampled| (m), hist L1 distance of the range CDFs (m), F1 hit/miss F1."
        + (f" Added as: {', '.join(details)}." if details else ""),
    )
    added = figure_table("parameters each step adds", "parameter", ("value",))
    for table, table_rows in ((steps, figures), (added, parameters)):
        for table_row in table_rows:
            table.add_row(*table_row)
    return Group(steps, *notes, added)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", nargs="?", default="reports/ouster_loop", help="report folder (default: %(default)s)")
    out = Path(parser.parse_args().out)
    console = Console()
    start = time.perf_counter()
    say = lambda message: console.print(f"[{time.perf_counter() - start:6.1f} s] {message}", markup=False)  # noqa: E731
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
    print_verdict(verdict(found))  # its **name** in bold, as the CLI prints it

    # 3. add effects, watch the error fall
    path = ouster_development_path(log, progress=say)
    console.print(path_tables(path.rows, "Ouster OS-1-32 frame: test rays (odd columns), 1 cm bins"))
    console.print("final model: " + ", ".join(effect.describe() for effect in path.model.effects))  # kept steps only

    # 4. compare again
    report("final", path.mesh, path.model, test_log, out, say)
