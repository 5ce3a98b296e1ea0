"""``python -m bench``: run every benchmark, print one table and write ``bench/results/*.md``."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from . import bench_calibrate, bench_core, bench_dataset, bench_diagnose, bench_fit_scene, bench_io


def _rows(run):
    """Adapt a benchmark returning row dicts to :class:`bench_core.Row`."""
    return lambda: [bench_core.Row(**row) for row in run()]


# results file stem -> function returning table rows
BENCHMARKS = {
    "core": bench_core.run,
    "calibrate": _rows(bench_calibrate.run),
    "fit_scene": _rows(bench_fit_scene.run),
    "io": _rows(bench_io.run),
    "diagnose": _rows(bench_diagnose.run),
    "dataset": _rows(bench_dataset.run),
}
RESULTS = Path(__file__).resolve().parent / "results"
COLUMNS = ("benchmark", "Mrays/s", "vs raw ray_intersect", "vs Open3D", "target", "pass/fail")


def _cells(row: bench_core.Row) -> list[str]:
    """Table cells of one row."""

    def ratio(value):
        return "" if value is None else f"{value:.2f}x"

    verdict = {True: "PASS", False: f"FAIL ({row.failed})", None: ""}[row.passed]
    rate = row.value if row.mrays is None else f"{row.mrays:.1f}"
    return [row.benchmark, rate, ratio(row.vs_raw), ratio(row.vs_open3d), row.target, verdict]


def _machine(start_load: float) -> str:
    """One line on the machine and its load (other processes slow every number down)."""
    import drjit as dr
    import mitsuba as mi

    load = f"{start_load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end"
    return (
        f"{platform.node()} ({os.cpu_count()} CPUs, benchmarks pinned to {bench_core.CORES}), "
        f"mitsuba {mi.__version__} / drjit {dr.__version__} ({mi.variant()}), load average {load}, "
        f"{time.strftime('%Y-%m-%d %H:%M')}"
    )


def _markdown(rows: list[bench_core.Row], header: str) -> str:
    """The rows as a Markdown table under ``header``."""
    lines = [f"# {header}", "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_cells(row)) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Run the benchmarks, print the table and write one Markdown file per benchmark."""
    console = Console(width=200)
    table = Table(
        title="mi-lidar benchmarks (rays per second: median of "
        f"{bench_core.REPEATS} runs after a warm-up, ~1M rays each)"
    )
    for column in COLUMNS:
        table.add_column(column, justify="left" if column in ("benchmark", "target") else "right")
    RESULTS.mkdir(exist_ok=True)
    for stem, run in BENCHMARKS.items():
        start_load = os.getloadavg()[0]
        with console.status(f"running the {stem} benchmarks"):
            rows = run()
        header = f"{stem} benchmarks: {_machine(start_load)}"
        (RESULTS / f"{stem}.md").write_text(_markdown(rows, header))
        for row in rows:
            table.add_row(*_cells(row), style={True: "green", False: "red", None: None}[row.passed])
        console.print(header)
    console.print(table)
    console.print(f"written to {RESULTS}/")


if __name__ == "__main__":
    main()
