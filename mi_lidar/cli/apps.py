"""The ``evaluate-apps`` verb: judge simulators by the applications developed on their scans."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.table import Table

from mi_lidar.cli.app import app, carmen_log_argument, console, max_range_option
from mi_lidar.cli.progress import progress


@app.command("evaluate-apps", rich_help_panel="The loop")
def evaluate_apps(
    log: Path = carmen_log_argument(),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder: apps.json, apps.html, PNGs, cache/."),
    max_range: float | None = max_range_option(),
    simulator: list[str] | None = typer.Option(
        None, "--simulator", "-s", help="Only these simulators (repeatable): M0 M1 P-Reg NP-Reg mi-lidar (default)."
    ),
    draws: int = typer.Option(16, min=2, help="Prior draws of each application's parameters for the risk."),
    runs: int = typer.Option(
        8,
        min=1,
        help="Runs of the trackers (EKF, particle filter) per setting, paired across sources; also the scans each "
        "simulator samples per state.",
    ),
    workers: int | None = typer.Option(
        None, min=1, help="Processes running the three applications side by side (default: one per core, up to 3)."
    ),
    test_every: int = typer.Option(5, min=2, help="Every k-th scan is a test state (the planar protocol)."),
    window: float = typer.Option(30.0, min=0.0, help="A state's map leaves out the scans within 1 m and this many s."),
):
    """Run scan-to-map registration (EKF) and particle-filter localization along the whole log, and line
    detection on its test scans, on the real scans and on scans simulated at the same states by each
    simulator; print the application-level risk with its standard error.

    The simulators are fitted on the training scans by the planar benchmark (`benchmark-planar`): M0 is the
    ray cast + one Gaussian (Gazebo-style), M1 the classic beam model, then P-Reg, NP-Reg and mi-lidar's
    permeable map. Reruns reuse OUT/cache; a run stopped half-way resumes there.

    Examples:

        mi-lidar evaluate-apps ../shared/data/carmen/intel-corrected.log.gz --out reports/intel-apps

        mi-lidar evaluate-apps building.log.gz --out reports/building -s M0 -s mi-lidar --draws 8
    """
    from mi_lidar.apps.evaluate import SIMULATORS, evaluate_log
    from mi_lidar.planar.protocol import PlanarProtocol

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
        )
    console.print(
        risk_table(
            f"{log.name}: application-level risk, mean |J real - J sim| over {draws} draws ± standard error "
            "(lower is better)",
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


def risk_table(title: str, simulators, rows) -> Table:
    """The risk table printed by the ``evaluate-apps`` verbs: one row per application, the lowest risk in bold.

    Args:
        title: table title.
        simulators: the column names.
        rows: ``(application, risk, standard error, picks)`` per application, each keyed by simulator;
            ``picks[name]['within']`` says whether the development path's setting is within 10 % of the
            best real J.
    """
    table = Table(
        title=title,
        caption="pick: the setting a developer reaches on the simulator; 'ok' when its real J is within 10 % of "
        "the best real J found",
        header_style="bold",
    )
    table.add_column("application", no_wrap=True)
    for name in simulators:
        table.add_column(name, justify="right", no_wrap=True)
    for application, risk, se, picks in rows:
        best = min(risk.values())
        cells = []
        for name in simulators:
            value = f"{risk[name]:.3g}\n± {se[name]:.1g}\npick {'ok' if picks[name]['within'] else 'off'}"
            cells.append(f"[bold]{value}[/bold]" if risk[name] == best else value)
        table.add_row(application, *cells)
    return table
