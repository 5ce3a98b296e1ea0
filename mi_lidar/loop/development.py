"""A development path on measured rays: effects added one by one, each fitted on calibration rays, scored on test rays.

:class:`Scored` holds a scene traced once with its rays; :func:`effect_step` refits a model's effects
and scores it, giving one :class:`Step` (a row of the path's table): the NLL beside the
realism of a scan sampled at the same rays (:func:`~mi_lidar.core.metrics.metrics_of`). With a
*realism guard*, an effect is kept only when it lowers the calibration NLL without making the
calibration samples less realistic (:func:`~mi_lidar.core.metrics.worse_samples`: histogram match,
F1, Chamfer distance and its stray half); otherwise the
row says why and the model goes back to what it was. Used by the real-frame loop
(:mod:`mi_lidar.loop.real_ouster`); the planar real-log benchmark lives in :mod:`mi_lidar.planar`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mitsuba as mi
import numpy as np

from mi_lidar.core.effects.base import Effect
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.metrics import metrics_of, worse_samples
from mi_lidar.core.params import Snapshot
from mi_lidar.core.problem import Problem, fit_parts
from mi_lidar.core.rays import LogRays, world_rays
from mi_lidar.core.sensor_model import SensorModel


@dataclass
class Scored:
    """A stacked scene with its scored rays: traced once, scored with :meth:`SensorModel.log_likelihood`.

    Attributes:
        scene: the loaded scene of every layer's elements.
        table: its element table.
        rays: the layers' scans as rays (layer ``j`` is scan ``j`` of the stacked log).
        n_elements: elements in the scene.
    """

    scene: object
    table: ElementTable
    rays: LogRays
    n_elements: int
    _problem: Problem | None = field(default=None, repr=False)

    @property
    def problem(self) -> Problem:
        """Every ray of the layers, traced once (:class:`~mi_lidar.core.problem.Problem`)."""
        if self._problem is None:
            self._problem = Problem.build(self.scene, self.rays, table=self.table)
        return self._problem

    def per_beam(self, model: SensorModel) -> np.ndarray:
        """(N,) scored log-likelihood per beam (nats, 1 cm range bins, the one floor) under ``model``."""
        return self.problem.log_likelihood(model)

    def nll(self, model: SensorModel) -> float:
        """Mean negative log-likelihood per beam (nats) under ``model``."""
        return self.problem.nll(model)

    def samples(self, model: SensorModel, seed: int = 0) -> dict:
        """NLL and the realism of one scan sampled by ``model`` at these rays (:func:`metrics_of`)."""
        from mi_lidar.loop.compare import simulate_log_rays

        sim_range, sim_hit = simulate_log_rays(self.scene, self.table, self.rays, model, seed)
        r = self.rays
        origins, directions = world_rays(r.log, r.scan, r.beam, r.column)
        return metrics_of(self.per_beam(model), r.measured, r.hit, sim_range, sim_hit, origins, directions)

    def fit(self, model: SensorModel, effects: list[Effect], steps: int = 150) -> None:
        """Fit ``effects`` (members of ``model.effects``) on these rays by maximum likelihood (:func:`fit_parts`)."""
        fit_parts(model, self.problem, effects, steps=steps)


@dataclass
class Step:
    """One row of a development path.

    Attributes:
        model: what was scored.
        added: the effect or change this step adds.
        nll: mean negative log-likelihood per test beam, nats.
        train_nll: the same on the calibration beams, nats.
        fitted: fitted parameters, ``{"effect.param": value}``.
        samples: realism of a scan sampled at the test beams (:func:`metrics_of`).
        rejected: why the realism guard did not keep the step ("" when kept).
    """

    model: str
    added: str
    nll: float
    train_nll: float
    fitted: dict
    samples: dict = field(default_factory=dict)
    rejected: str = ""


def describe_effects(effects: list[Effect]) -> dict:
    """``{"effect.param": first value}`` of every parameter of ``effects``."""
    return {f"{e.name}.{k}": float(np.asarray(v)[0]) for e in effects for k, v in e.params.items()}


def fit_and_score(
    train: Scored, test: Scored, model: SensorModel, fit: list[Effect], steps: int
) -> tuple[float, float]:
    """Fit ``fit`` (effects of ``model``) on ``train``, then return the test and training NLL (nats/beam)."""
    if fit:
        train.fit(model, fit, steps=steps)
    return test.nll(model), train.nll(model)


def effect_step(
    model_name: str, label: str, train: Scored, test: Scored, model: SensorModel, steps: int, say, guard=None
) -> Step:
    """Refit every effect of ``model`` on ``train``, score it on ``test``: the development-path row ``+ label``.

    Args:
        model_name, label: the row's model and what it adds.
        train, test: calibration and test rays.
        model: the model with the new effect appended (changed in place).
        steps: Adam steps.
        say: ``say(message)`` progress.
        guard: the previous step's ``(calibration NLL, calibration samples)`` for the realism guard, or None
            to keep the step whatever it does. A guarded step that does not lower the calibration NLL, or
            makes the calibration samples less realistic (:func:`worse_samples`), is marked rejected and
            the model is restored (last effect removed, the others' parameters as before).
    """
    saved = Snapshot(model.effects)
    nll, train_nll = fit_and_score(train, test, model, model.effects, steps)
    row = Step(model_name, f"+ {label}", nll, train_nll, describe_effects(model.effects), test.samples(model))
    if guard is not None:
        before_nll, before_samples = guard
        worse = worse_samples(before_samples, train.samples(model))
        if train_nll >= before_nll or worse:
            row.rejected = (
                "calibration NLL did not fall"
                if train_nll >= before_nll
                else "samples worse: " + ", ".join(f"{k} {a:.3g} -> {b:.3g}" for k, (a, b) in worse.items())
            )
            model.effects = model.effects[:-1]
            saved.restore()
    say(f"+ {label}: {nll:.3f}" + (f" (not kept: {row.rejected})" if row.rejected else ""))
    return row


def ray_subset(rays: LogRays, keep: np.ndarray) -> LogRays:
    """The rays of ``rays`` where ``keep`` holds (ray ids stay the log's flat indices)."""
    index = np.flatnonzero(keep)
    return _IndexedRays(
        log=rays.log,
        scan=rays.scan[index],
        beam=rays.beam[index],
        column=rays.column[index],
        time=rays.time[index],
        measured=rays.measured[index],
        hit=rays.hit[index],
        ids=index,
    )


@dataclass
class _IndexedRays(LogRays):
    """A subset of a log's rays that keeps the log's flat ray ids."""

    ids: np.ndarray = None

    def batch(self, index: np.ndarray | None = None):
        index = np.arange(self.n) if index is None else np.asarray(index)
        rays, measured, hit = LogRays.batch(self, index)  # the subset's rays, then the log's ray ids
        rays.ray_id = mi.UInt32(self.ids[index].astype(np.uint32))
        return rays, measured, hit
