"""The ``fit-sensor`` verb: fit a learned sensor model (P-Reg, NP-Reg, beam, physics) to a log."""

from __future__ import annotations

from pathlib import Path

import typer

from mi_lidar.cli.app import MAX_STEPS, app, console, force_option, log_argument, warn
from mi_lidar.cli.progress import note, progress
from mi_lidar.cli.tables import rows_table


@app.command("fit-sensor", rich_help_panel="The loop")
def fit_sensor_command(
    log: Path = log_argument(),
    scene: Path = typer.Argument(..., help="Scene XML the log was recorded in.", exists=True, dir_okay=False),
    model: str = typer.Option(
        "np-reg", "--model", "-m", help="Family: np-reg, p-reg, beam or physics (any case: NP-Reg is np-reg)."
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output density file (`.npz`)."),
    steps: int = typer.Option(200, metavar="N", min=1, max=MAX_STEPS, help="Adam steps (beam, physics)."),
    seed: int = typer.Option(0, metavar="N", min=0, help="Seed of the split and of the sampled scan."),
    pool_labels: bool = typer.Option(
        False, "--pool-labels", help="NP-Reg and P-Reg: one law per range and incidence, whatever the element label."
    ),
    force: bool = force_option("Fit"),
):
    """Fit a return density to a log in its scene; print held-out NLL beside sample realism; save it.

    Reference the result from the scene's integrator:
    `<string name="density" value="np_reg(file=sensor.npz)"/>`.

    Examples:

    ```
    mi-lidar fit-sensor drive.npz scenes_xml/offroad.xml --model np-reg \\
        --out sensor.npz

    mi-lidar fit-sensor drive.npz scenes_xml/offroad.xml -m p-reg -o p_reg.npz
    ```

    With --pool-labels an NP-Reg or P-Reg density applies to scenes whose labels mean other classes (a density
    fitted off-road, used in a street).
    """
    from mi_lidar.io import read_any
    from mi_lidar.loop.sensor_fit import fit_sensor, save_sensor

    model = model.lower()  # benchmark-planar and the docs write NP-Reg, P-Reg
    with progress(f"fitting {model}"):
        result = fit_sensor(
            read_any(log),
            scene,
            model,
            steps=steps,
            seed=seed,
            pool_labels=pool_labels,
            progress=note,
            force=force,
        )
        path = save_sensor(result, out)
    table = rows_table(
        f"{log.name}: {result.test_rays:,} held-out rays",
        "model",
        (
            ("test NLL", "nll"),
            ("train NLL", "train_nll"),
            ("median |err|", "range_error_median"),
            ("p90 |err|", "range_error_p90"),
            ("F1", "f1"),
            ("hist L1", "histogram_l1"),
        ),
        result.rows,
        caption="NLL: nats per ray; |err|: a sampled scan vs the measured one where both returned (m); F1: "
        "hit/miss agreement of that scan; hist L1: distance of the range CDFs (m)",
    )
    warn(result.warnings)
    console.print(table)
    console.print(f"wrote {path}")
