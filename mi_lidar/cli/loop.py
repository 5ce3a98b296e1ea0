"""Verbs of the loop: ``compare`` a model with a log and ``diagnose`` what it lacks."""

from __future__ import annotations

from pathlib import Path

import typer

from mi_lidar.cli.app import MAX_STEPS, app, console, density_option, force_option, log_argument, say, warn
from mi_lidar.cli.progress import progress


@app.command("compare", rich_help_panel="The loop")
def compare_command(
    log: Path = log_argument(),
    scene: Path = typer.Argument(
        ...,
        help="Scene XML of the model (its sensor and integrator settings and effects).",
        exists=True,
        dir_okay=False,
    ),
    out: Path = typer.Option(
        ..., "--out", "-o", help="Report folder: report.md/.html, PNG plots, residual image, residuals.ply."
    ),
    seed: int = typer.Option(0, metavar="N", min=0, help="Seed of the simulated scan."),
    force: bool = force_option("Compare"),
    density: str | None = density_option(),
):
    """Compare the model with a measured log ray by ray: NLL, range error, hit/miss F1, histogram match, and where it
    fails worst.

    Examples:

    ```
    mi-lidar compare room.npz scenes_xml/indoor_planar.xml \\
        --out reports/before
    ```
    """
    from mi_lidar.io import read_any
    from mi_lidar.loop import compare as run
    from mi_lidar.loop.compare import group_name
    from mi_lidar.scene import load_scene, use_density

    with progress("simulating the log's rays and comparing"):
        result = run(read_any(log), use_density(load_scene(scene), density), out=out, seed=seed, force=force)
    head = result.headline
    warn(result.warnings)
    console.print(
        f"NLL {head['nll']:.3f} nats/ray, hit/miss F1 {head['f1']:.3f}; worst: "
        f"{group_name(result.worst[0])} ({result.worst[0]['nll']:.2f} nats/ray)"
    )
    if result.intensity is not None:
        i = result.intensity.metrics()
        console.print(
            f"{result.intensity.channel}: NLL {i['intensity_nll']:.3f} nats/return, "
            f"measured / model median {i['intensity_ratio']:.2f} over {i['returns']:,} returns"
        )
    console.print(f"report: {out / 'report.html'}")


@app.command("diagnose", rich_help_panel="The loop")
def diagnose_command(
    log: Path = log_argument(),
    scene: Path = typer.Argument(..., help="Scene XML of the current model.", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Report folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the ranking as JSON (for scripts)."),
    candidate: list[str] | None = typer.Option(
        None,
        "--candidate",
        help="Only try these effects or learned densities (np-reg, p-reg) (repeatable), by name or as the ranking "
        "prints them, e.g. `incidence_dropout(law=cos)`; default: the whole catalog.",
    ),
    steps: int = typer.Option(
        60,
        metavar="N",
        min=1,
        max=MAX_STEPS,
        help="Adam steps per candidate fit at most (a fit stops once it stops gaining).",
    ),
    force: bool = force_option("Diagnose"),
    density: str | None = density_option(),
):
    """Find the physical effects the model lacks: fit every candidate on training rays, rank and confirm them by a
    held-out test, and say what the residuals still vary with. The report folder gets diagnosis.html (rankings,
    likelihood beside the realism of samples, a before/after figure per effect found, residual structure) and
    scene.xml, the scene with the effects found (and a learned density's tables when one replaced the density).

    Examples:

    ```
    mi-lidar diagnose room.npz scenes_xml/indoor_planar.xml \\
        --out reports/diagnosis

    mi-lidar diagnose room.npz scenes_xml/indoor_planar.xml --out d --json \\
        --candidate incidence_dropout --candidate outliers
    ```
    """
    from mi_lidar.core.strict_json import dumps
    from mi_lidar.io import read_any
    from mi_lidar.loop import diagnose as run
    from mi_lidar.scene import load_scene, use_density

    with progress("diagnose") as update:
        result = run(
            read_any(log),
            use_density(load_scene(scene), density),
            out=out,
            candidates=candidate or None,
            steps=steps,
            progress=lambda i, n, label: update(i, n, label),
            force=force,
        )
    from mi_lidar.scene.files import scene_with_effects

    density = None
    if result.density is not None:  # a learned density replaced the scene's: save it beside the scene, which names
        saved = result.density.save(out / f"{result.density.name}.npz", notes={"from": "mi-lidar diagnose"})
        density = f"{result.density.name}(file={Path(saved).name})"  # it relative to itself: the folder moves whole
    effects = ", ".join(e.describe() for e in result.model.effects)
    found = scene_with_effects(scene, effects, out / "scene.xml", density)
    if as_json:
        typer.echo(dumps(result.ranking(), indent=1, default=float))
    else:
        say(result.summary)
        console.print(f"report: {out / 'diagnosis.html'}; the scene with the model's effects: {found}")
