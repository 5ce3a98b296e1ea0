"""The ``evaluate-apps`` verb: judge simulators by the applications developed on their scans."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.console import Group
from rich.table import Table
from rich.text import Text

from mi_lidar.cli.app import app, carmen_log_argument, carmen_message_option, console, max_range_option
from mi_lidar.cli.progress import progress
from mi_lidar.cli.tables import FIGURE_WIDTH

MAX_DRAWS = 1000  # prior draws of the risk: its standard error shrinks as 1 / sqrt(draws), the run time grows with them


@app.command("evaluate-apps", rich_help_panel="The loop")
def evaluate_apps(
    log: Path = carmen_log_argument(),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder: apps.json, apps.html, PNGs, cache/."),
    max_range: float | None = max_range_option(),
    message: str | None = carmen_message_option(),
    simulator: list[str] | None = typer.Option(
        None,
        "--simulator",
        "-s",
        help="Only these simulators (repeatable, any case): M0 M1 P-Reg NP-Reg mi-lidar (default).",
    ),
    draws: int = typer.Option(
        16, metavar="N", min=2, max=MAX_DRAWS, help="Prior draws of each application's parameters for the risk."
    ),
    runs: int = typer.Option(
        8,
        metavar="N",
        min=1,
        max=32,
        help="Runs of the trackers (EKF, particle filter) per setting, paired across sources (at most 32, the most "
        "a tracker runs per setting); also the scans each simulator samples per state.",
    ),
    workers: int | None = typer.Option(
        None,
        metavar="N",
        min=1,
        max=3,
        help="Processes running the three applications side by side (default: one per core, up to 3).",
    ),
    test_every: int = typer.Option(
        5, metavar="N", min=3, help="Every k-th scan is a test state (the planar protocol)."
    ),
    window: float = typer.Option(
        30.0, metavar="X", min=0.0, help="A state's map leaves out the scans within 1 m and this many s."
    ),
):
    """Run scan-to-map registration (EKF) and particle-filter localization along the whole log, and line
    detection on its test scans, on the real scans and on scans simulated at the same states by each
    simulator; print the application-level risk with its standard error.

    The simulators are fitted on the training scans by the planar benchmark (`benchmark-planar`): M0 is the
    ray cast + one Gaussian (Gazebo-style), M1 the classic beam model, then P-Reg, NP-Reg and mi-lidar's
    permeable map. Reruns reuse OUT/cache; a run stopped half-way resumes there.

    Examples:

    ```
    mi-lidar evaluate-apps ../shared/data/carmen/intel-corrected.log.gz \\
        --out reports/intel-apps

    mi-lidar evaluate-apps building.log.gz --out reports/building -s M0 \\
        -s mi-lidar --draws 8
    ```
    """
    from mi_lidar.apps.evaluate import SIMULATORS, evaluate_log
    from mi_lidar.core.resources import map_large_blocks
    from mi_lidar.planar.protocol import PlanarProtocol

    map_large_blocks()  # freed arrays go back to the system (workers fork after): Intel's peak 1.76 -> 1.43 GB
    with progress(f"evaluate-apps {log.name}") as update:
        result = evaluate_log(
            log,
            out,
            max_range,
            PlanarProtocol(test_every=test_every, window=window),
            tuple(simulator) if simulator else SIMULATORS,
            draws=draws,
            runs=runs,
            workers=workers or min(3, os.cpu_count() or 1),
            progress=lambda done, total, label: update(done, total, label),
            message=message,
        )
    console.print(
        risk_table(
            f"{log.name}: application-level risk",
            f"mean |J real - J sim| over {draws} draws ± standard error",
            result.simulators,
            [(r.name, r.risk, r.risk_se, r.picks) for r in result.results],
        )
    )
    for r in result.results:
        console.print(f"{r.name}: J = {r.objective}; best real J found {r.best_real[0]:.4g}")
    seconds = result.seconds
    console.print(
        f"{result.states.n} states ({int(result.states.test.sum())} test scans); {seconds['total']:.0f} s "
        f"({seconds['total_cpu']:.0f} CPU s); report: {out / 'apps.html'}"
    )


def risk_table(title: str, risk: str, simulators, rows) -> Group:
    """The risk table printed by the ``evaluate-apps`` verbs, with its legend below it: one row per simulator, one
    column per application, the lowest risk of each application in bold.

    Simulators are rows so that the table keeps to 80 columns however many are compared (six in 3D); the
    legend is a paragraph of its own, as wide as the terminal.

    Args:
        title: table title.
        risk: what a risk is, e.g. ``mean |J real - J sim| over 16 draws ± standard error``.
        simulators: the row names.
        rows: ``(application, risk, standard error, picks)`` per application, each keyed by simulator;
            ``picks[name]['within']`` says whether the development path's setting is within 10 % of the
            best real J.
    """
    table = Table(title=title, header_style="bold")
    table.add_column("simulator", no_wrap=True)
    for application, *_ in rows:
        table.add_column(application, justify="right", min_width=FIGURE_WIDTH)
    for name in simulators:
        cells = []
        for _, risks, se, picks in rows:
            value = f"{risks[name]:.3g} ± {se[name]:.1g}\npick {'ok' if picks[name]['within'] else 'off'}"
            cells.append(f"[bold]{value}[/bold]" if risks[name] == min(risks.values()) else value)
        table.add_row(name, *cells)
    legend = Text(
        f"risk: {risk}, lower is better (the lowest of each application in bold); pick: the setting a developer "
        "reaches on the simulator, 'ok' when its real J is within 10 % of the best real J found",
        style="dim",
    )
    return Group(table, legend)
