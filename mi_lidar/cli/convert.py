"""Verbs on sensor files: ``convert`` and ``info``."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from mi_lidar.cli.app import app, console

MODEL_HELP = (
    "Velodyne model (VLP-16, VLP-32C, HDL-32E); default: the packets' product byte, checked against the "
    "packet timing and the calibration table."
)


def _reader_options(metadata: Path | None, calibration: Path | None, model: str | None) -> dict:
    options = (("metadata", metadata), ("calibration", calibration), ("model", model))
    return {k: v for k, v in options if v is not None}


@app.command(rich_help_panel="Sensor files")
def convert(
    source: Path = typer.Argument(
        ...,
        help="Input: .pcap (Ouster/Velodyne), CARMEN .log[.gz], .bin, .ply, .pcd, .las, ROS 2 bag folder, "
        ".npz log, .exr.",
        exists=True,
    ),
    target: Path = typer.Argument(..., help="Output file; its extension picks the format unless --to is given."),
    to: str | None = typer.Option(None, help="Output format: npz, bin, ply, pcd, las, rosbag2, exr, png."),
    scan: int | None = typer.Option(
        None, metavar="N", min=0, help="Scan to write when the output holds one scan (required for multi-scan logs)."
    ),
    metadata: Path | None = typer.Option(None, help="Ouster metadata JSON (default: next to the pcap)."),
    calibration: Path | None = typer.Option(None, help="Velodyne calibration YAML (default: next to the pcap)."),
    model: str | None = typer.Option(None, help=MODEL_HELP),
):
    """Convert a Lidar file to another format, keeping misses explicit where the format allows.

    Examples:

    ```
    mi-lidar convert ../shared/data/carmen/intel-corrected.log.gz intel.npz

    mi-lidar convert ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.pcap \\
        frame.pcd --scan 0

    mi-lidar convert drive.npz drive_bag --to rosbag2
    ```
    """
    from mi_lidar.io import convert as run

    with console.status(f"converting {source.name}"):
        path = run(source, target, to=to, scan=scan, **_reader_options(metadata, calibration, model))
    console.print(f"wrote {path}")


@app.command(rich_help_panel="Sensor files")
def info(
    source: Path = typer.Argument(..., help="Any file `convert` reads.", exists=True),
    metadata: Path | None = typer.Option(None, help="Ouster metadata JSON (default: next to the pcap)."),
    calibration: Path | None = typer.Option(None, help="Velodyne calibration YAML (default: next to the pcap)."),
    model: str | None = typer.Option(None, help=MODEL_HELP),
):
    """Summarise a Lidar file: sensor, beams, firings, scans, miss fraction, range span, pose extents.

    Examples:

    ```
    mi-lidar info ../shared/data/velodyne/velodyne_vlp16.pcap

    mi-lidar info capture.pcap --model HDL-32E --calibration 32db.yaml

    mi-lidar info drive.npz
    ```
    """
    from mi_lidar.io import info as run

    with console.status(f"reading {source.name}"):
        summary = run(source, **_reader_options(metadata, calibration, model))
    table = Table(title=str(source.name), show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    s, h, w = summary["shape"]
    rows = [
        ("format", summary["format"]),
        ("sensor", summary["sensor"]),
        ("scans x beams x firings", f"{s} x {h} x {w}"),
        ("rays", f"{summary['rays']:,}"),
        ("miss fraction", f"{summary['miss_fraction']:.1%}"),
        ("invalid cells", f"{summary['invalid_fraction']:.1%}"),
    ]
    if summary["range_m"]:
        rows.append(("range min / median / max (m)", " / ".join(f"{v:.2f}" for v in summary["range_m"])))
    if summary["no_return_m"] is not None:
        no_return = summary["no_return_m"]
        rows.append(("no-return value (m)", f"{no_return:.2f}" if no_return < float("inf") else "none in the log"))
    rows.append(("time span (s)", f"{summary['time_span_s']:.3f}"))
    if summary["scan_period_s"] is not None:
        rows.append(("scan period (s)", f"{summary['scan_period_s']:.3f}"))
    elif s > 1:
        rows.append(("scan period (s)", "unknown (no whole scan)"))
    if summary["simulated"] is not None:
        effects = ", ".join(summary["simulated"]["effects"]) or "none"
        rows.append(("simulated with", f"seed {summary['simulated']['seed']}; effects: {effects}"))
    rows.append(("trajectory length (m)", f"{summary['trajectory_length_m']:.2f}"))
    rows.append(("attributes", ", ".join(summary["attributes"]) or "-"))
    for row in rows:
        table.add_row(*row)
    console.print(table)
