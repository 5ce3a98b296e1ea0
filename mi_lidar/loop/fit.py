"""Fit effect parameters by maximum likelihood (Adam on the pass-through mixture).

A small, self-contained fitter for the loop: it fits the parameters of chosen effects of a
:class:`~mi_lidar.sensor_model.SensorModel` to measured rays with :class:`mi.ad.Adam`, and scores
rays with :meth:`SensorModel.log_likelihood`. Each parameter is optimised in units of its scale
(``Effect.fit_scales[name]``, default 0.1) and clipped to its :class:`ParamSpec` bounds after
every step. Parameters listed in ``Effect.fit_exclude`` stay fixed; parameters listed in
``Effect.per_label`` (and per-beam parameters) are widened to one value per label (beam) first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..effects.base import Effect
from ..elements import ElementTable
from ..segment import SURFACE
from ..sensor_model import SensorModel
from .rays import LogRays

LL_FLOOR = -30.0  # nats: per-ray log-likelihood floor in the fitting loss (keeps gradients finite)
DEFAULT_SCALE = 0.1
BATCH = 1 << 18  # rays scored at once


class PlaneTable(ElementTable):
    """An element table whose surface ranges follow the traced tangent plane.

    Surface ranges become ``t = dot(p - o, n) / dot(d, n)`` with the traced point ``p`` and normal
    ``n`` held fixed, so that gradients with respect to the ray origin ``o`` and direction ``d``
    (beam offsets, extrinsics, motion) are those of the surface, not of the fixed traced point.
    """

    @classmethod
    def of(cls, table: ElementTable) -> "PlaneTable":
        """Wrap an existing table (arrays shared)."""
        return cls(**{k: getattr(table, k) for k in table.__dataclass_fields__})

    def segment(self, si, valid, element, origin, direction, default_sigma: float):
        seg = super().segment(si, valid, element, origin, direction, default_sigma)
        n = dr.detach(si.n)
        denom = dr.dot(direction, n)
        safe = dr.select(dr.abs(denom) > 1e-6, denom, 1e-6)
        t = dr.dot(dr.detach(si.p) - origin, n) / safe
        surface = seg.kind == SURFACE
        return seg.with_(nominal=dr.select(surface, t, seg.nominal), mean=dr.select(surface, seg.mean - seg.nominal + t, seg.mean))


def widen(effect: Effect, n_beams: int, n_labels: int) -> Effect:
    """Give per-beam parameters ``n_beams`` values and per-label ones ``n_labels`` (in place)."""
    for key, spec in effect.specs.items():
        size = n_beams if spec.per_beam else n_labels if key in getattr(effect, "per_label", ()) else 1
        values = np.asarray(effect.params[key])
        if values.size == 1 and size > 1:
            effect.params[key] = mi.Float(np.full(size, values[0], np.float32))
    return effect


def fitted_names(effect: Effect) -> list[str]:
    """Names of the parameters of ``effect`` that fitting changes."""
    return [k for k in effect.specs if k not in getattr(effect, "fit_exclude", ())]


def n_parameters(effects: list[Effect]) -> int:
    """Number of scalar fitted parameters of ``effects``."""
    return int(sum(dr.width(e.params[k]) for e in effects for k in fitted_names(e)))


@dataclass
class Problem:
    """Measured rays of one split, traced once, ready to score and fit.

    Attributes:
        scene: loaded Mitsuba scene.
        table: its element table (a :class:`PlaneTable`).
        rays: the log's rays.
        index: (N,) indices (into ``rays``) of the rays of this split.
        resolution: range bin (m) of the discretized score; 0 scores densities.
    """

    scene: object
    table: ElementTable
    rays: LogRays
    index: np.ndarray
    resolution: float = 0.0
    _chunks: list = field(default_factory=list, repr=False)

    @classmethod
    def build(cls, scene, rays: LogRays, index: np.ndarray, resolution: float = 0.0) -> "Problem":
        return cls(scene=scene, table=PlaneTable.of(ElementTable.from_scene(scene)), rays=rays,
                   index=np.asarray(index), resolution=resolution)

    def trace(self, model: SensorModel) -> None:
        """Trace every chunk of the split under ``model`` (its ray perturbations included)."""
        self._chunks = []
        for first in range(0, self.index.size, BATCH):
            batch, measured, hit = self.rays.batch(self.index[first:first + BATCH])
            records = model.trace_segments(self.scene, self.table, batch)
            self._chunks.append((batch, measured, hit, records))

    def log_likelihood(self, model: SensorModel) -> np.ndarray:
        """(N,) per-ray log-likelihood (nats) under ``model`` (traces first if needed)."""
        if not self._chunks:
            self.trace(model)
        out = []
        with dr.suspend_grad():
            for batch, measured, hit, records in self._chunks:
                ll = model.log_likelihood(self.table, batch, records, measured, hit, self.resolution)
                out.append(np.asarray(ll, dtype=np.float64))
        return np.concatenate(out) if out else np.zeros(0)


@dataclass
class FitResult:
    """Outcome of :func:`fit_effects`.

    Attributes:
        history: mean log-likelihood per ray (nats) at each step.
        parameters: fitted values, ``{"effect.param": np.ndarray}``.
    """

    history: list[float]
    parameters: dict[str, np.ndarray]


def fit_effects(model: SensorModel, problem: Problem, effects: list[Effect] | None = None, steps: int = 150,
                lr: float = 0.1, retrace_every: int = 50, progress=None) -> FitResult:
    """Maximise the mean log-likelihood of ``problem``'s rays over effect parameters.

    Args:
        model: sensor model holding the effects (changed in place: fitted values are written
            into the effects' ``params``).
        problem: the measured rays (traced on demand).
        effects: effects to fit (default: all of ``model.effects``).
        steps: Adam steps.
        lr: learning rate in units of each parameter's scale (decays to lr/10, cosine).
        retrace_every: steps between re-traces when an effect perturbs rays.
        progress: optional callable ``progress(step, steps)``.

    Returns:
        The loss history and the fitted parameters.
    """
    effects = model.effects if effects is None else effects
    slots = [(e, k) for e in effects for k in fitted_names(e)]
    if not slots:
        return FitResult(history=[], parameters={})
    moves_rays = any(type(e).perturb_rays is not Effect.perturb_rays for e in model.effects)
    start = {(id(e), k): np.asarray(e.params[k], dtype=np.float32) for e, k in slots}
    opt = mi.ad.Adam(lr=lr)
    for i, (e, k) in enumerate(slots):
        opt[f"{i}"] = dr.zeros(mi.Float, dr.width(e.params[k]))

    def assign():
        for i, (e, k) in enumerate(slots):
            spec = e.specs[k]
            scale = getattr(e, "fit_scales", {}).get(k, DEFAULT_SCALE)
            value = mi.Float(start[(id(e), k)]) + scale * opt[f"{i}"]
            e.params[k] = dr.clip(value, max(spec.lower, -1e30), min(spec.upper, 1e30))

    history = []
    n = max(problem.index.size, 1)
    for step in range(steps):
        if step == 0 or (moves_rays and step % retrace_every == 0):
            with dr.suspend_grad():
                assign()
            problem.trace(model)
        opt.set_learning_rate(lr * (0.1 + 0.45 * (1 + math.cos(math.pi * step / steps))))
        total = 0.0
        for batch, measured, hit, records in problem._chunks:
            assign()  # a fresh graph per chunk: backward releases the previous one
            ll = model.log_likelihood(problem.table, batch, records, measured, hit, problem.resolution)
            loss = -dr.sum(dr.maximum(ll, LL_FLOOR)) / n
            dr.backward(loss)
            total += float(loss[0])
        opt.step()
        history.append(-total)
        if progress is not None:
            progress(step + 1, steps)
    with dr.suspend_grad():
        assign()
    for e, k in slots:
        e.params[k] = mi.Float(np.asarray(dr.detach(e.params[k]), dtype=np.float32))
    if moves_rays:
        problem.trace(model)
    return FitResult(history=history, parameters={f"{e.name}.{k}": np.asarray(e.params[k]) for e, k in slots})
