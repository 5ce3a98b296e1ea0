"""The ``benchmark-planar`` verb: score every sensor model on a real planar log with the real-planar protocol."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from mi_lidar.cli.app import app, carmen_log_argument, carmen_message_option, console, max_range_option, warn
from mi_lidar.cli.progress import progress
from mi_lidar.cli.tables import figure, figure_table
from mi_lidar.planar.settings import PlanarProtocol

PROTOCOL = PlanarProtocol()  # the defaults of the command's protocol options


@app.command("benchmark-planar", rich_help_panel="The loop")
def benchmark_planar(
    log: Path = carmen_log_argument(),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder: benchmark.json, benchmark.html, PNGs."),
    max_range: float | None = max_range_option(),
    message: str | None = carmen_message_option(),
    test_every: int = typer.Option(PROTOCOL.test_every, metavar="N", min=3, help="Every k-th scan is a test scan."),
    cell: float = typer.Option(PROTOCOL.cell, metavar="X", min=0.005, max=1.0, help="Map cell (m)."),
    radius: float = typer.Option(
        PROTOCOL.radius, metavar="X", min=0.0, help="A test scan's map leaves out scans within this distance (m) ..."
    ),
    window: float = typer.Option(PROTOCOL.window, metavar="X", min=0.0, help="... and within this time (s) of it."),
    train_beams: int = typer.Option(
        PROTOCOL.train_beams,
        metavar="N",
        min=0,
        help="Fit on at most this many training beams (evenly spaced scans of a longer log; 0: all).",
    ),
    model: list[str] | None = typer.Option(
        None,
        "--model",
        "-m",
        help="Only these models (repeatable, any case): M0 M1 M2a M2b M3a M3b P-Reg NP-Reg mi-lidar.",
    ),
):
    """Fit every sensor model on the training scans of a planar log and score it on the test scans.

    Runs the real-planar protocol (docs/benchmark_planar.md): leave-out maps per scan, a 5 cm occ3 map,
    1 cm scoring. Prints NLL per beam, miss F1 and the realism of sampled scans for the ray cast + Gaussian
    (M0), the beam models (M1, M2a, M2b), the binned histograms (M3a, M3b), P-Reg, NP-Reg and mi-lidar's
    permeable map.

    Examples:

    ```
    mi-lidar benchmark-planar ../shared/data/carmen/intel-corrected.log.gz \\
        --out reports/intel

    mi-lidar benchmark-planar building.log.gz --out reports/building \\
        --max-range 50
    ```
    """
    from mi_lidar.core.resources import map_large_blocks
    from mi_lidar.planar.benchmark import MODELS, SAMPLED_SCANS, benchmark_file
    from mi_lidar.planar.report import REFERENCE

    map_large_blocks()  # freed arrays go back to the system: Intel's peak 1.84 -> 1.42 GB
    with progress(f"benchmark {log.name}") as update:
        result = benchmark_file(
            log,
            out,
            max_range,
            PlanarProtocol(cell=cell, test_every=test_every, radius=radius, window=window, train_beams=train_beams),
            tuple(model) if model else MODELS,
            progress=lambda done, total, label: update(done, total, label),
            message=message,
        )
    scores = figure_table(
        f"{log.name}: {result.data.test.n:,} test beams",
        "model",
        ("test NLL", "train NLL", "NLL hits", "NLL misses", "miss F1"),
        caption="nats per beam; miss F1: P(miss) above a threshold tuned on the training beams",
    )
    samples = figure_table(
        "Sampled test scans",
        "model",
        ("median |err|", "p90 |err|", "F1", "hist L1", "CRPS mean", "CRPS median"),
        caption="|err|: one sampled scan vs the measured one where both returned (m); F1: hit/miss agreement "
        f"of that scan; hist L1: distance of the range CDFs (m), the mean over {SAMPLED_SCANS} sampled scans (that "
        "of the first one and each model's standard errors are in the report); CRPS: continuous ranked "
        f"probability score per beam from {SAMPLED_SCANS} sampled scans (m; a no-return counts as "
        f"{result.no_return:g} m), lowest in expectation for the sensor's own law; last row: the measured test "
        "scans re-paired between beams of like nominal range, what a model that samples like the sensor scores "
        "(a reference, not a model)",
    )

    def sample_figures(s: dict) -> tuple[str, ...]:
        keys = ("range_error_median", "range_error_p90", "f1", "histogram_l1_draws", "crps_mean")
        return (*(figure(s[k]) for k in keys), figure(s["crps_median"], 4))

    for r in result.rows:
        scores.add_row(
            r.name, *(figure(v) for v in (r.test_nll, r.train_nll, r.nll_hits, r.nll_misses, r.miss_tuned["f1"]))
        )
        samples.add_row(r.name, *sample_figures(r.samples), end_section=r is result.rows[-1])
    if result.reference:  # none for one test scan (a warning says so)
        samples.add_row(REFERENCE, *sample_figures(result.reference))
    console.print(scores)
    console.print(samples)
    for label, key in (("hist L1", "histogram_l1_draws"), ("CRPS mean", "crps_mean")):
        console.print(lowest_and_runner_up(result.rows, label, key, SAMPLED_SCANS))
    warn(result.warnings())
    if result.data.train.n < result.train_beams_in_log:
        console.print(
            f"fitted on {result.data.train.n:,} of the log's {result.train_beams_in_log:,} training beams "
            "(evenly spaced scans; --train-beams 0 fits on all)"
        )
    no_return = result.data.log.sensor["max_range_m"]
    console.print(
        (f"no-return value {no_return:g} m" if no_return < float("inf") else "no no-return value in the log")
        + f" (give it with --max-range); {result.seconds['total']:.0f} s; report: {out / 'benchmark.html'}"
    )


def lowest_and_runner_up(rows: list, label: str, key: str, draws: int) -> str:
    """One line: the model of the lowest ``key`` (a sample figure with its standard error from the ``draws``
    sampled scans, ``key + "_se"``), how far below the runner-up, and whether the draws tell the two apart
    (the difference above twice its standard error)."""
    ranked = sorted(rows, key=lambda r: r.samples[key])
    if len(ranked) < 2:
        return f"{label}: {ranked[0].name} {ranked[0].samples[key]:.3f} ± {ranked[0].samples[key + '_se']:.3f} m"
    best, second = ranked[0].samples, ranked[1].samples
    gap, se = second[key] - best[key], math.hypot(best[key + "_se"], second[key + "_se"])
    verdict = "told apart" if gap > 2.0 * se else "not told apart"
    return (
        f"{label}: {ranked[0].name} lowest, {gap:.3f} m below {ranked[1].name} "
        f"(± {se:.3f} m from the {draws} draws: {verdict})"
    )
