"""The ``calibrate`` verb: fit scene and sensor parameters to a log by Dr.Jit autodiff."""

from __future__ import annotations

import math
from pathlib import Path

import typer
from rich.console import Group
from rich.table import Table
from rich.text import Text

from mi_lidar.calibration.commands import calibrate_command
from mi_lidar.calibration.report import SHARED_KEPT
from mi_lidar.calibration.result import FitResult
from mi_lidar.cli.app import MAX_STEPS, app, console, force_option, warn
from mi_lidar.cli.progress import progress
from mi_lidar.cli.tables import FIGURE_WIDTH, figure, figure_table
from mi_lidar.core.atomic import output_folder
from mi_lidar.io.markdown import plain, spread_figures

FIT = "Fit"  # the options of the optimisation, a panel of their own: the option column stays narrow


def result_table(result: FitResult) -> Group:
    """Rich tables: the parameter changes; the spread of the fitted values of each parameter of more than one
    value (per beam, per element); the held-out loss of the initial, counting, shared-start (when run) and fitted
    models.

    A parameter name longer than its column folds onto a second line instead of being cut.
    """
    changes = Table(title="calibration", header_style="bold")
    changes.add_column("parameter", overflow="fold")
    for column in ("values", "mean\nbefore", "mean\nafter", "max\n|change|"):  # two-line headers: room for the names
        changes.add_column(column, justify="right", min_width=FIGURE_WIDTH)
    for name in result.names:
        before, after = result.initial[name], result.fitted[name]
        changes.add_row(
            name, f"{before.size:,}", plain(before.mean()), plain(after.mean()), plain(abs(after - before).max())
        )
    many = [name for name in result.names if result.fitted[name].size > 1]
    spreads = figure_table("fitted values", "parameter", ("min", "median", "max", "RMS"))
    for name in many:
        spreads.add_row(name, *(plain(float(v)) for v in spread_figures(result.fitted[name]).values()))
    losses = figure_table(
        "held-out NLL",
        "model",
        ("nats/ray",),
        caption=f"after {result.steps_run} Adam steps" + (" (early stop)" if result.stopped_early else ""),
    )
    kept = [Text(SHARED_KEPT)] if result.shared and result.shared_nll == result.fitted_nll else []
    rows = [("initial", result.initial_nll), ("counting", result.counting_nll)]
    rows += [("shared start", result.shared_nll)] if result.shared else []
    for name, nll in rows + [("fitted", result.fitted_nll)]:
        losses.add_row(name, figure(nll, 4))  # as report.html writes it
    return Group(changes, *([spreads] if many else []), losses, *kept)


@app.command(rich_help_panel="The loop")
def calibrate(
    log: Path = typer.Argument(..., help="Measured log (any format `convert` reads).", exists=True),
    scene: Path = typer.Argument(
        ..., help="Scene XML whose `lidar` sensor recorded the log.", exists=True, dir_okay=False
    ),
    params: list[str] = typer.Option(
        ..., "--params", "-p", help="Parameter glob; repeat for more, e.g. `elements.*.p_hit`, `sensor.*`."
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
    steps: int = typer.Option(200, metavar="N", min=1, max=MAX_STEPS, help="Maximum Adam steps.", rich_help_panel=FIT),
    batch_size: int = typer.Option(1 << 16, metavar="N", min=1, help="Training rays per step.", rich_help_panel=FIT),
    holdout: float = typer.Option(
        0.2, help="Fraction of rays held out for validation and early stopping.", rich_help_panel=FIT
    ),
    seed: int = typer.Option(
        0, metavar="N", min=0, help="Seed of the split and of the mini-batch draws.", rich_help_panel=FIT
    ),
    lr: list[str] | None = typer.Option(
        None, "--lr", metavar="GLOB=RATE", help="Learning rate override; repeatable.", rich_help_panel=FIT
    ),
    lr_scale: float = typer.Option(1.0, help="Factor on every learning rate.", rich_help_panel=FIT),
    patience: int = typer.Option(
        5,
        metavar="N",
        min=1,
        help="Held-out evaluations without improvement before stopping.",
        rich_help_panel=FIT,
    ),
    no_counting_start: bool = typer.Option(
        False,
        "--no-counting-start",
        help="Start hit probabilities from the scene's, not from the counting estimate hits/(hits+pass-throughs).",
        rich_help_panel=FIT,
    ),
    no_shared_start: bool = typer.Option(
        False,
        "--no-shared-start",
        help="Fit per-beam parameters (range bias, beam angle offsets) beam by beam from the start, not first as "
        "one value shared by all beams.",
        rich_help_panel=FIT,
    ),
    pattern: str | None = typer.Option(
        None,
        help="Firing pattern of the log's sensor when it is not the scene sensor's: `log` (the log's own rays, "
        "e.g. a planar CARMEN log), a pattern name or a .csv/.npy table. The calibrated scene fires it.",
    ),
    force: bool = force_option("Calibrate"),
):
    """Fit scene and sensor parameters to a log by Dr.Jit autodiff; write the calibrated scene and a report.

    Parameter names: `elements.<shape>.p_hit|range_sigma|centers|scales`, `classes.<label>.range_sigma`,
    `terrain.<shape>.heights`, `sensor.elevation_offset|azimuth_offset|range_bias|range_scale|extrinsics`,
    `effects.<effect>.<parameter>`.

    Examples:

    ```
    mi-lidar calibrate drive.npz scenes_xml/offroad.xml \\
        --params 'elements.*.p_hit' --out out/cal

    mi-lidar calibrate drive.npz scene.xml -p 'sensor.elevation_offset' \\
        -p 'sensor.range_bias' --out out/intrinsics

    mi-lidar calibrate building.log.gz building.xml -p 'elements.*.p_hit' \\
        --pattern log --out out/building
    ```
    """
    # No total yet: it is known when the fit starts (twice the steps with a shared start), from the first update on.
    with output_folder(out), progress("calibrating") as update:  # nothing left when the run fails
        held = {"text": ""}  # the held-out NLL is evaluated every few steps: show the last one, none before the first

        def report(step, total, train, held_out):
            if math.isfinite(held_out):
                held["text"] = f" | held-out {held_out:.4f} nats/ray"
            update(step, total, f"calibrating: loss {train:.4f}{held['text']}")

        result, files = calibrate_command(
            log,
            scene,
            params,
            out,
            steps=steps,
            batch_size=batch_size,
            holdout=holdout,
            seed=seed,
            lr=lr,
            lr_scale=lr_scale,
            patience=patience,
            progress=report,
            counting_start=not no_counting_start,
            shared_start=not no_shared_start,
            pattern=pattern,
            force=force,
        )
    warn(result.warnings)
    console.print(result_table(result))
    for path in files.values():
        console.print(f"wrote {path}")
