"""The ``dataset`` verb: camera + Lidar datasets in KITTI layout, rendered on Dask, resumable."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from mi_lidar.cli.app import app, console
from mi_lidar.cli.progress import progress

MAX_RETRIES = 100  # extra attempts of a failing frame: a frame that fails 100 times will not pass on the 101st


@app.command(rich_help_panel="Make scans")
def dataset(
    spec: Path = typer.Argument(..., help="Dataset spec (.yaml or .toml); see docs/datasets.md.", dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (KITTI layout + manifest.json)."),
    scheduler: str | None = typer.Option(
        None, help="Address of an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a LocalCluster)."
    ),
    workers: int | None = typer.Option(
        None,
        metavar="N",
        min=1,
        max=os.cpu_count(),
        help="LocalCluster worker processes (default and most: one per core).",
    ),
    serial: bool = typer.Option(False, "--serial", help="Render in this process, in frame order, without Dask."),
    retries: int = typer.Option(
        2, metavar="N", min=0, max=MAX_RETRIES, help="Extra attempts of a failing frame before it is reported."
    ),
    dashboard: str = typer.Option(":8787", help="LocalCluster dashboard address ('' for none)."),
):
    """Render a camera + Lidar dataset: KITTI layout, SemanticKITTI labels, manifest with digests; resumable.

    Runs one Dask task per frame on a LocalCluster sized to the machine (or on --scheduler). Run the
    same command again after an interruption: frames in the manifest are verified by digest and skipped.
    `street_quick.yaml` runs as it is; `street_and_forest.yaml` reads a primitive library and a sensor
    model that the four commands in its header make first (about 2 CPU minutes).

    Examples:

    ```
    mi-lidar dataset examples/datasets/street_quick.yaml \\
        --out out/street_quick

    mi-lidar dataset examples/datasets/street_and_forest.yaml \\
        --out out/street_forest

    mi-lidar dataset spec.yaml --out /shared/ds \\
        --scheduler tcp://10.0.0.5:8786
    ```
    """
    from mi_lidar.dataset import load_spec, run_dataset

    loaded = load_spec(spec)
    scenes = len(loaded.scenes)
    console.print(f"{loaded.name}: {loaded.frames:,} frames from {scenes:,} scene{'s' * (scenes != 1)} -> {out}")
    with progress("frames", total=loaded.frames) as update:
        report = run_dataset(
            loaded,
            out,
            scheduler=scheduler,
            workers=workers,
            serial=serial,
            retries=retries,
            dashboard_address=dashboard or None,
            progress=lambda done, total: update(done),
            announce=lambda message: console.print(message, highlight=False, markup=False),
        )
    table = Table(title=f"{loaded.name} in {out}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for name, value in (
        ("frames in the spec", report.total),
        ("kept from an earlier run (digests verified)", report.skipped),
        ("rendered now", report.rendered),
        ("failed after retries", len(report.failed)),
        ("partial files removed", report.removed_partial),
        ("wall time (s)", f"{report.seconds:.1f}"),
        ("frames per minute (rendered now)", f"{60 * report.rendered / max(report.seconds, 1e-9):.1f}"),
        ("CPU seconds per frame (rendered now)", f"{report.cpu_seconds / max(report.rendered, 1):.2f}"),
    ):
        table.add_row(name, str(value))
    console.print(table)
    for index, error in sorted(report.failed.items()):
        console.print(f"[red]frame {index} failed:[/red] {escape(error)}")
    if report.failed:
        console.print("run the same command again to retry the failed frames")
        raise typer.Exit(1)
