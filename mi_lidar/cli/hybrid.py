"""Verbs of hybrid geometric scenes (thesis ch. 4): ``synth-world``, ``fit-scene``, ``primitives``,
``annotate`` and ``compose``."""

from __future__ import annotations

from pathlib import Path

import typer

from mi_lidar.cli.app import FriendlyGroup, app, console
from mi_lidar.cli.progress import progress
from mi_lidar.cli.render import scan_summary


@app.command("synth-world", rich_help_panel="Hybrid scenes")
def synth_world(
    out: Path = typer.Option(
        ..., "--out", "-o", help="Output log (`.npz`) with ground-truth `label` and `instance` per ray."
    ),
    seed: int = typer.Option(11, metavar="N", min=0, help="World seed (layout, objects, noise)."),
    length: float = typer.Option(
        100.0, metavar="X", min=20.0, max=10_000.0, help="World length along the vehicle path (m)."
    ),
    width: float = typer.Option(
        50.0, metavar="X", min=20.0, max=10_000.0, help="World width (m; trees need 20 m at least)."
    ),
    spacing: float = typer.Option(1.5, metavar="X", min=0.1, help="Distance between scans along the path (m)."),
):
    """Generate a synthetic off-road world (terrain, trees and shrubs of leaf triangles, grass, rocks) and log a drive
    through it with a true sensor (beam divergence, mixed pixels, dropouts).

    Examples:

    ```
    mi-lidar synth-world --out train.npz --seed 11

    mi-lidar synth-world --out test.npz --seed 22 --length 120
    ```
    """
    from mi_lidar.hybrid.true_sensor import path_poses, render_log
    from mi_lidar.hybrid.world import WorldSpec, make_world

    with progress("building the world and logging the drive"):
        world = make_world(seed, WorldSpec(length=length, width=width))
        log = render_log(world, path_poses(world, spacing), seed=seed)
        path = log.save(out)
    console.print(scan_summary(log, f"synthetic world (seed {seed})"))
    console.print(f"wrote {path}")


@app.command("fit-scene", rich_help_panel="Hybrid scenes")
def fit_scene(
    log: Path = typer.Argument(
        ...,
        help="A 3D log (`.npz` from `mi-lidar synth-world`, any format `convert` reads), or a planar log with world "
        "poses (a SLAM-corrected CARMEN `.log.gz`).",
        exists=True,
        dir_okay=False,
    ),
    out: Path = typer.Option(
        ..., "--out", "-o", help="Output folder for the scene XML, its assets (`<name>_assets/`) and previews."
    ),
    name: str = typer.Option("scene", help="Scene name (XML file stem)."),
    cell: float | None = typer.Option(
        None, metavar="X", min=0.005, max=1.0, help="Planar logs: the wall map's cell (m); default 0.05."
    ),
):
    """Fit a scene to a log: a hybrid geometric scene (ground triangles + vegetation ellipsoids with hit
    probabilities) to a 3D log, a permeable wall map to a planar log.

    A planar log's map (docs/tutorial_loop.md, "The loop on a real planar log"): every 5 cm cell that a return ended
    in holds a wall 1 m tall around the scan plane that stops a beam with the share of the beams reaching it that
    stopped there, in the log's world frame: a surface through the cell's returns where the returns around it lie on
    a line, the cell's box elsewhere; the sensor fires the log's pattern up to its no-return value. Scored on the log
    it was built from (`compare`, `fit-sensor`, `diagnose`) the map is in-sample: every return has a wall at its
    end.

    Examples:

    ```
    mi-lidar fit-scene train.npz --out fitted/

    mi-lidar fit-scene ../shared/data/carmen/intel-corrected.log.gz \\
        --out intel/
    ```
    """
    from mi_lidar.core.atomic import output_folder
    from mi_lidar.core.errors import ParameterError
    from mi_lidar.hybrid.commands import fit_scene as fit_hybrid
    from mi_lidar.io.dispatch import read_any
    from mi_lidar.planar.map_scene import CELL, fit_map_scene

    loaded = read_any(log)
    if not loaded.is_planar and cell is not None:
        raise ParameterError(f"--cell {cell:g}: {log} is a 3D log; --cell sets a planar log's wall map")
    with output_folder(out):  # nothing left when the run fails
        if loaded.is_planar:
            written = fit_map_scene(loaded, out, name=name, cell=CELL if cell is None else cell)
        else:
            written = fit_hybrid(loaded, out, name=name)
    for path in written:
        console.print(f"wrote {path}")


primitives_app = typer.Typer(
    cls=FriendlyGroup, help="The primitive library: labeled objects cut from fitted scenes.", no_args_is_help=True
)
app.add_typer(primitives_app, name="primitives", rich_help_panel="Hybrid scenes")


@primitives_app.command("extract")
def primitives_extract(
    log: Path = typer.Argument(..., help="Labeled log (`.npz`).", exists=True, dir_okay=False),
    library: Path = typer.Option(..., "--library", "-l", help="Library folder (created or extended)."),
):
    """Fit the log, cut it into labeled objects and store each as a primitive at the identity pose.

    Example:

    ```
    mi-lidar primitives extract train.npz --library lib/
    ```
    """
    from mi_lidar.hybrid.commands import primitives_extract as run

    console.print(f"{library}: {len(run(log, library).primitives):,} primitives")


@primitives_app.command("list")
def primitives_list(library: Path = typer.Argument(..., help="Library folder.", exists=True, file_okay=False)):
    """List the primitives of a library as a table.

    Example:

    ```
    mi-lidar primitives list lib/
    ```
    """
    from mi_lidar.hybrid.commands import primitives_list as run

    run(library, console)  # one table, on stdout


@primitives_app.command("show")
def primitives_show(
    library: Path = typer.Argument(..., help="Library folder.", exists=True, file_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output PNG."),
    per_class: int = typer.Option(4, metavar="N", min=1, help="Primitives shown per class."),
):
    """Draw primitives of every class into one PNG.

    Example:

    ```
    mi-lidar primitives show lib/ --out lib.png
    ```
    """
    from mi_lidar.hybrid.commands import primitives_show as run

    console.print(f"wrote {run(library, out, per_class=per_class)}")


@app.command(rich_help_panel="Hybrid scenes")
def annotate(
    log: Path = typer.Argument(..., help="Labeled log (`.npz`).", exists=True, dir_okay=False),
    out: Path = typer.Option(..., "--out", "-o", help="Output annotation JSON (class, pose and box per object)."),
):
    """Write the annotation (class, pose, box per object) of a labeled log.

    Example:

    ```
    mi-lidar annotate test.npz --out test_annotation.json
    ```
    """
    from mi_lidar.hybrid.commands import annotate as run

    for path in run(log, out):
        console.print(f"wrote {path}")


@app.command(rich_help_panel="Hybrid scenes")
def compose(
    annotation: Path = typer.Argument(
        ..., help="Annotation JSON (from `mi-lidar annotate` or written by hand).", exists=True, dir_okay=False
    ),
    library: Path = typer.Option(
        ..., "--library", "-l", help="Primitive library folder.", exists=True, file_okay=False
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output scene XML."),
):
    """Build a new scene from an annotation: per object, the primitive of its class with the closest box, placed at its
    pose.

    Example:

    ```
    mi-lidar compose test_annotation.json --library lib/ --out composed.xml
    ```
    """
    from mi_lidar.hybrid.commands import compose as run

    for path in run(annotation, library, out):
        console.print(f"wrote {path}")
