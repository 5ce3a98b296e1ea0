"""Run ``diagnose`` on a log of an independent simulator and check what it names, how large, how fast."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.core.log import Log
from mi_lidar.loop import diagnose
from mi_lidar.scene.loading import load_scene


@dataclass
class Outcome:
    """What diagnose said about one hidden-effect log.

    Attributes:
        first: the first round's best candidate.
        selected: the effects that joined, in order.
        parameters: fitted values of the selected effects (``{"effect.param": array}``).
        flagged: dimensions the residual test flagged.
        significant_rows: rows marked significant in the first round.
        seconds: wall-clock time of the diagnosis (for the results table, never asserted).
        summary: the verdict.
        scene, log, model: the scene and log diagnosed, and the final model.
    """

    first: str
    selected: list
    parameters: dict
    flagged: list
    significant_rows: list
    seconds: float
    summary: str
    scene: object = field(repr=False, default=None)
    log: Log | None = field(repr=False, default=None)
    model: object = field(repr=False, default=None)


def run_case(arrays: dict, xml: str, folder: Path, **options) -> Outcome:
    """Write the scene, build the log from ``arrays`` and diagnose it (``options`` go to :func:`diagnose`)."""
    path = Path(folder) / "scene.xml"
    path.write_text(xml)
    scene = load_scene(path)
    log = Log(**arrays, sensor={"name": "hidden-effect test"})
    start = time.perf_counter()
    d = diagnose(log, scene, **options)
    seconds = time.perf_counter() - start
    return Outcome(
        first=d.rounds[0][0].name if d.rounds and d.rounds[0] else "",
        selected=[name.split("(")[0] for name in d.selected],
        parameters={k: np.asarray(v, float) for k, v in d.parameters.items()},
        flagged=d.flagged(),
        significant_rows=[c.name for c in d.rounds[0] if c.significant] if d.rounds else [],
        seconds=seconds,
        summary=d.summary,
        scene=scene,
        log=log,
        model=d.model,
    )


def relative_error(fitted, truth) -> float:
    """Largest |fitted - truth| / |truth| over the entries (truth nonzero)."""
    fitted, truth = np.asarray(fitted, float), np.asarray(truth, float)
    return float(np.max(np.abs(fitted - truth) / np.abs(truth)))
