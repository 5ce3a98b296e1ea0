"""``mi-lidar calibrate`` as a plain function: read the log and scene, fit, write the outputs."""

from __future__ import annotations

from pathlib import Path

from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.calibration.report import write_report
from mi_lidar.calibration.result import FitResult
from mi_lidar.core.errors import MiLidarError
from mi_lidar.core.patterns import get_pattern
from mi_lidar.core.patterns.from_log import pattern_from_log
from mi_lidar.io import read_any
from mi_lidar.scene.loading import load_scene


def parse_learning_rates(items: list[str] | None) -> dict[str, float]:
    """``["elements.*.p_hit=0.05", ...]`` -> ``{glob: lr}``; raise :class:`MiLidarError` on a bad item."""
    rates = {}
    for item in items or []:
        glob, eq, value = item.rpartition("=")
        try:
            rates[glob] = float(value)
        except ValueError:
            eq = ""
        if not eq or not glob:
            raise MiLidarError(f"--lr {item!r}: write GLOB=RATE, e.g. --lr 'sensor.range_bias=0.002'")
    return rates


def calibrate_command(
    log,
    scene,
    params: list[str],
    out,
    steps: int = 200,
    batch_size: int = 1 << 16,
    holdout: float = 0.2,
    seed: int = 0,
    lr: list[str] | None = None,
    lr_scale: float = 1.0,
    patience: int = 5,
    eval_every: int = 10,
    counting_start: bool = True,
    shared_start: bool = True,
    progress=None,
    pattern: str | None = None,
    force: bool = False,
) -> tuple[FitResult, dict[str, Path]]:
    """Fit the parameters ``params`` (globs) of ``scene`` to ``log`` and write the outputs to ``out``.

    Args:
        log: path of a log in any format ``convert`` reads (``.npz``, CARMEN ``.log[.gz]``, ...).
        scene: path of the scene XML (its ``lidar`` sensor must be the log's unless ``pattern``
            says which sensor recorded the log).
        params: parameter globs, e.g. ``["elements.*.p_hit", "sensor.range_bias"]``.
        out: output folder: ``scene.xml`` (+ ``scene_assets/``), ``loss.png``, ``changes.csv``,
            ``history.csv``, ``parameters.npz``, ``report.json``.
        steps, batch_size, holdout, seed, patience, eval_every, counting_start, shared_start: see
            :class:`~mi_lidar.calibration.fit.FitOptions`.
        lr: learning-rate overrides ``GLOB=RATE``.
        lr_scale: factor on every learning rate.
        progress: optional ``progress(step, steps, train_loss, held_out_loss)`` callback.
        pattern: the log's firing pattern when it is not the scene sensor's: ``"log"`` (the log's
            own rays, e.g. a planar CARMEN log), a pattern name or a ``.csv``/``.npy`` table; the
            calibrated scene's sensor fires it.
        force: fit even when the log's sensor does not match the scene's.

    Returns:
        The fit result and the written files by kind.

    Raises:
        MiLidarError: unreadable inputs, a glob matching nothing, a log from another sensor, or a
            diverging loss (each message says what to change).
    """
    measured = read_any(log)
    loaded = load_scene(scene)
    firing = None
    if pattern is not None:
        firing = (
            pattern_from_log(measured, name=f"{Path(log).stem}-pattern") if pattern == "log" else get_pattern(pattern)
        )
    options = FitOptions(
        steps=steps,
        batch_size=batch_size,
        holdout=holdout,
        seed=seed,
        patience=patience,
        eval_every=eval_every,
        learning_rates=parse_learning_rates(lr),
        lr_scale=lr_scale,
        counting_start=counting_start,
        shared_start=shared_start,
    )
    calibration = Calibration(loaded, measured, list(params), options=options, pattern=firing, force=force)
    result = calibration.fit(progress)
    units = {n: calibration.params[n].unit for n in result.names}
    title = f"calibrate {Path(log).name} in {Path(scene).name}"
    files = write_report(out, result, loaded, units, title=title, pattern=firing)
    return result, files
