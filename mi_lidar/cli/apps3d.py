"""The ``evaluate-apps-3d`` verb: judge 3D simulators by scan matching on a real frame and on their scans."""

from __future__ import annotations

from pathlib import Path

import typer

from mi_lidar.cli.app import MAX_STEPS, app, console
from mi_lidar.cli.apps import MAX_DRAWS, risk_table
from mi_lidar.cli.progress import progress
from mi_lidar.cli.tables import rows_table


@app.command("evaluate-apps-3d", rich_help_panel="The loop")
def evaluate_apps_3d(
    capture: Path = typer.Argument(
        ..., exists=True, dir_okay=False, help="An Ouster or Velodyne pcap (or any one-frame log mi-lidar reads)."
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder: apps3d.json, apps3d.html, PNGs, cache/."),
    simulator: list[str] | None = typer.Option(
        None,
        "--simulator",
        "-s",
        help="Only these simulators (repeatable, any case): gaussian physics beam P-Reg NP-Reg mi-lidar "
        "(default: all).",
    ),
    draws: int = typer.Option(
        16, metavar="N", min=2, max=MAX_DRAWS, help="Prior draws of the registration parameters for the risk."
    ),
    starts: int = typer.Option(
        8, metavar="N", min=2, max=100, help="Seeded initial-pose errors each registration starts from."
    ),
    steps: int = typer.Option(
        1500, metavar="N", min=10, max=MAX_STEPS, help="Adam steps per fit of the mi-lidar development path."
    ),
    seed: int = typer.Option(0, metavar="N", min=0, help="Seed of the sampled scans, the starts and the prior draws."),
):
    """Register the real scan and every simulator's scan of the same rays to the same real map (small_gicp,
    from the same perturbed starts); print the application-level risk of each simulator.

    The frame's range image is split by columns: a mesh from columns 0 mod 4 is the scene, the simulators
    are fitted on columns 2 mod 4 (whose measured points are also the map), and the odd columns are the
    scan. gaussian is the ray cast + one Gaussian (Gazebo-style), beam the classic beam model, mi-lidar the
    model the loop calibrates. Reruns reuse OUT/cache.

    Examples:

    ```
    mi-lidar evaluate-apps-3d \\
        ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.pcap \\
        --out reports/ouster-apps

    mi-lidar evaluate-apps-3d capture.pcap --out reports/vlp -s gaussian \\
        -s mi-lidar --draws 8
    ```
    """
    from mi_lidar.apps.evaluate3d import evaluate_frame
    from mi_lidar.apps.frames import SIMULATORS

    with progress(f"evaluate-apps-3d {capture.name}") as update:
        result = evaluate_frame(
            capture,
            out,
            tuple(simulator) if simulator else SIMULATORS,
            draws=draws,
            starts=starts,
            seed=seed,
            steps=steps,
            progress=lambda done, total, label: update(done, total, label),
        )
    console.print(
        risk_table(
            f"{capture.name}: 3D registration risk",
            f"mean |J real - J sim| over {draws} draws ± bootstrap standard error over the starts",
            result.simulators,
            [(r.name, r.risk, result.risk_se[r.name], r.picks) for r in result.results],
        )
    )
    samples = rows_table(
        "the simulators on the test rays: NLL and the realism of their samples",
        "simulator",
        (
            ("NLL", "nll"),
            ("median |err|", "range_error_median"),
            ("p90 |err|", "range_error_p90"),
            ("F1", "f1"),
            ("hist L1", "histogram_l1"),
            ("Chamfer", "chamfer"),
        ),
        result.benchmark,
        caption="NLL: nats per ray; |err|: the sampled scan vs the measured one where both returned (m); F1: "
        "hit/miss agreement; hist L1: distance of the range CDFs (m); Chamfer: distance of the point clouds (m)",
    )
    console.print(samples)
    for r in result.results:
        console.print(f"{r.name}: J = {r.objective}; best real J found {r.best_real[0]:.4g}")
    console.print(f"{result.seconds['total']:.0f} s; report: {out / 'apps3d.html'}")
