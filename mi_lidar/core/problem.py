"""Measured rays of a log, traced once, scored and fitted with the one likelihood and the one fitter.

A :class:`Problem` holds the rays of one split of a log (``index``) in a scene. :meth:`Problem.trace`
traces them once per distinct set of ray-moving parameters into compact rounds
(:mod:`mi_lidar.core.trace`), in chunks of :data:`BATCH` rays; when nothing moves rays, each entry's
return distribution is computed once too. :meth:`Problem.log_likelihood` scores every ray with
:func:`~mi_lidar.core.likelihood.score`, and :func:`fit_parts` fits the parameters of a model's
density and effects by :func:`~mi_lidar.core.fitting.adam_fit`, with each parameter's bounds, step
unit and starting value taken from its :class:`~mi_lidar.core.params.ParamSpec`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.fitting import FitVariable, adam_fit, cosine_schedule, fine_cosine_schedule
from mi_lidar.core.likelihood import mixture_log_likelihood, score
from mi_lidar.core.params import Parametrized
from mi_lidar.core.rays import LogRays, RayBatch
from mi_lidar.core.trace import cache_distributions, trace_rounds

BATCH = 1 << 18  # rays scored at once
LEARNING_RATE = 0.3  # Adam step in units of each parameter's scale (cosine decay to a tenth)
SURFACE_TOLERANCE = 0.5  # m: a return this close to an element its beam reaches lies on the scene's surface


def moves_rays(model) -> bool:
    """True when an effect of ``model`` edits rays before tracing (angle offsets, extrinsics, motion, footprint)."""
    return any(e.moves_rays for e in model.effects)


def _ray_key(model) -> tuple:
    """Identity of the rays ``model`` traces: its ray-moving effects and their parameter values."""
    return tuple(
        (e.name, tuple(np.asarray(dr.detach(v)).tobytes() for v in e.params.values()))
        for e in model.effects
        if e.moves_rays
    )


def make_opaque(parts: list[Parametrized]) -> None:
    """Turn the parts' parameters into opaque kernel inputs (in place).

    A width-1 array built from a Python or numpy value is a literal that Dr.Jit bakes into the
    kernel, so every new value would compile a new kernel; opaque values are read from memory.
    """
    for part in parts:
        for key, value in part.params.items():
            array = mi.Float(aligned(np.asarray(dr.detach(value), dtype=np.float32)))
            dr.make_opaque(array)
            part.params[key] = array


def n_parameters(parts: list[Parametrized]) -> int:
    """Number of scalar fitted parameters of ``parts``."""
    return int(sum(dr.width(p.params[k]) for p in parts for k in p.fitted_names()))


@dataclass
class Chunk:
    """Up to :data:`BATCH` rays of a split, traced into compact rounds.

    Attributes:
        rays: the measured rays (before the model's ray perturbations).
        z: (N,) measured range, m (0 for a miss).
        hit: (N,) True where the sensor reported a return.
        rounds: the trace (:class:`~mi_lidar.core.trace.Rounds`).
        intensity: (N,) measured intensities scored with the ranges (NaN for a miss), or None.
    """

    rays: RayBatch
    z: mi.Float
    hit: mi.Bool
    rounds: object
    intensity: mi.Float | None = None


@dataclass
class Problem:
    """Measured rays of one split, traced once, ready to score and fit.

    Attributes:
        scene: loaded Mitsuba scene.
        table: its element table.
        rays: the log's rays; None when another tracer traced them (``fixed``, see :meth:`from_rounds`).
        index: (N,) indices (into ``rays``) of the rays of this split.
        chunks: the traced chunks (see :meth:`trace`).
    """

    scene: object
    table: ElementTable
    rays: LogRays | None
    index: np.ndarray
    chunks: list = field(default_factory=list, repr=False)
    _traced: tuple | None = field(default=None, repr=False)
    _batches: list = field(default_factory=list, repr=False)  # the untraced chunks (:meth:`batches`)
    fixed: bool = False  # the chunks were traced by another tracer: never re-trace

    @classmethod
    def build(cls, scene, rays: LogRays, index: np.ndarray | None = None, table: ElementTable | None = None) -> Problem:
        """The problem of rays ``index`` of ``rays`` (all when None) in ``scene``."""
        index = np.arange(rays.n) if index is None else np.asarray(index)
        return cls(scene=scene, table=table or ElementTable.from_scene(scene), rays=rays, index=index)

    @classmethod
    def from_rounds(cls, table: ElementTable, rays: RayBatch, rounds, z: mi.Float, hit: mi.Bool) -> Problem:
        """A problem whose rays another tracer traced (e.g. a planar log's ray march): one fixed chunk.

        Models fitted on it must not move rays (their segments cannot be traced again).
        """
        chunk = Chunk(rays=rays, z=dr.select(hit, z, 0.0), hit=hit, rounds=rounds)
        return cls(scene=None, table=table, rays=None, index=np.arange(rays.width), chunks=[chunk], fixed=True)

    @property
    def n(self) -> int:
        return int(self.index.size)

    def trace(self, model) -> None:
        """Trace every chunk of the split under ``model`` (its ray perturbations included).

        Tracing is skipped when the rays ``model`` traces are those of the last trace (the same
        ray-moving effects with the same values, range limits and density), as they are for every
        effect that only edits segments. When nothing moves rays, each entry's return distribution
        before effects is computed once as well.
        """
        key = (_ray_key(model), model.max_range, model.max_segments, model.range_sigma)
        if self.fixed or self.rays is None:
            if moves_rays(model):
                raise ParameterError("this problem's rays were traced by another tracer: effects cannot move them")
            return
        if self._traced == key and self.chunks:
            return
        self.chunks = []
        moving = moves_rays(model)
        for batch in self.batches():
            rounds = trace_rounds(self.scene, self.table, model, batch.rays)
            if not moving:
                rounds = cache_distributions(rounds, self.table, model, batch.rays)
            self.chunks.append(dataclasses.replace(batch, rounds=rounds))
        self._traced = key

    def batches(self) -> list[Chunk]:
        """The split's rays in chunks of :data:`BATCH`, untraced (``rounds`` None), built once: every trace starts
        from the same rays (a fit of ray-moving parameters traces them again every few steps)."""
        rays = self.log_rays()
        if not self._batches:
            for first in range(0, self.n, BATCH):
                index = self.index[first : first + BATCH]
                batch, measured, hit = rays.batch(index)
                z = dr.select(hit, measured, 0.0)
                self._batches.append(Chunk(batch, z, hit, None, rays.measured_intensity(index)))
        return self._batches

    def log_rays(self) -> LogRays:
        """The log's rays of this problem.

        Raises:
            ParameterError: the problem was traced by another tracer (:meth:`from_rounds`) and holds no log rays.
        """
        if self.rays is None:
            raise ParameterError("this problem's rays were traced by another tracer: it holds no log rays")
        return self.rays

    def chunk_log_likelihood(self, model, chunk: Chunk) -> mi.Float:
        """Scored per-ray log-likelihood (nats) of one chunk under ``model`` (keeps gradients)."""
        ll = mixture_log_likelihood(self.table, model, chunk.rays, chunk.rounds, chunk.z, chunk.hit, chunk.intensity)
        return score(ll, chunk.hit)

    def log_likelihood(self, model) -> np.ndarray:
        """(N,) scored per-ray log-likelihood (nats) under ``model`` (:func:`~mi_lidar.core.likelihood.score`)."""
        self.trace(model)
        with dr.suspend_grad():
            out = [np.asarray(self.chunk_log_likelihood(model, c), np.float64) for c in self.chunks]
        return np.concatenate(out) if out else np.zeros(0)

    def log_likelihood_by_beam(self, model, n_beams: int) -> np.ndarray:
        """(n_beams,) scored log-likelihood (nats) of the rays summed beam by beam.

        Each ray belongs to one beam, so the likelihood is a sum of per-beam terms, and a per-beam
        parameter's values are judged all at once from one evaluation. Rays of beams beyond ``n_beams - 1``
        count to the last (a per-beam parameter of width 1 holds one value for every beam).
        """
        beams = np.minimum(self.log_rays().beam[self.index], n_beams - 1)
        return np.bincount(beams, weights=self.log_likelihood(model), minlength=n_beams)

    def nll(self, model) -> float:
        """Mean negative scored log-likelihood per ray (nats)."""
        return float(-np.mean(self.log_likelihood(model)))

    def near_surface(self, model, tolerance: float = SURFACE_TOLERANCE) -> np.ndarray | None:
        """(N,) True for the measured returns within ``tolerance`` (m) of an element their beam can reach.

        A beam reaches the elements traced along its ray up to and including the first opaque one
        (hit probability 1). False for misses. None when the model fans beams out into sub-rays (the
        trace then holds sub-rays, not the log's rays).
        """
        self.trace(model)
        opaque = np.asarray(self.table.p_hit) >= 1.0
        near = []
        for chunk in self.chunks:
            z, hit = np.asarray(chunk.z), np.asarray(chunk.hit)
            if chunk.rounds.width != z.size:
                return None
            ok, stopped = np.zeros(z.size, bool), np.zeros(z.size, bool)
            for entries in chunk.rounds.rounds:  # in order along the rays, one entry per ray at most
                ray, nominal = np.asarray(entries.ray), np.asarray(entries.nominal)
                reached = ray[~stopped[ray] & (np.abs(z[ray] - nominal) <= tolerance)]
                ok[reached] = True
                stopped[ray[opaque[np.asarray(entries.element)]]] = True
            near.append(ok & hit)
        return np.concatenate(near) if near else np.zeros(0, bool)


@dataclass
class PartsFit:
    """Outcome of :func:`fit_parts`.

    Attributes:
        history: mean scored log-likelihood per ray (nats) at each step.
        parameters: fitted values, ``{"part.param": np.ndarray}``.
    """

    history: list[float]
    parameters: dict[str, np.ndarray]


def fit_parts(
    model,
    problem: Problem,
    parts: list[Parametrized] | None = None,
    steps: int = 150,
    lr: float = LEARNING_RATE,
    retrace_every: int = 10,
    progress=None,
    tolerance: float | None = None,
    window: int | None = None,
) -> PartsFit:
    """Maximise the mean scored log-likelihood of ``problem``'s rays over the parameters of ``parts``.

    Args:
        model: the sensor model holding the parts (changed in place: the best values are written
            into the parts' ``params``, as opaque arrays).
        problem: the measured rays (traced on demand).
        parts: the density and/or effects of ``model`` to fit (default: every effect).
        steps: Adam steps.
        lr: learning rate in units of each parameter's ``fit_scale`` (cosine decay to lr / 10, to lr / 100
            when a fitted effect moves rays).
        retrace_every: steps between re-traces when a fitted effect moves rays.
        progress: optional callable ``progress(step, steps)``.
        tolerance: stop once the mean training log-likelihood (nats/ray) improved by less than this
            over the last 10 steps (``retrace_every + 5`` when a fitted effect moves rays), after 2 more
            (:func:`~mi_lidar.core.fitting.stalled`; None: run every step).
        window: the steps ``tolerance`` looks back instead (None: as above).

    Returns:
        The loss history and the fitted parameters: those of the lowest loss seen (the loss is over
        every ray, so a refit never ends worse than its start).
    """
    parts = model.effects if parts is None else parts
    make_opaque(model.parts)
    slots = [(part, key) for part in parts for key in part.fitted_names()]
    if not slots:
        return PartsFit(history=[], parameters={})
    names = [f"{part.name}.{key}#{i}" for i, (part, key) in enumerate(slots)]
    variables = [
        FitVariable(
            name,
            np.asarray(part.params[key], np.float64),
            lower=max(part.specs[key].fit_bound, -1e30),
            upper=min(part.specs[key].upper, 1e30),
            scale=part.fit_scale(key),
            transform=part.specs[key].fit_transform,
        )
        for name, (part, key) in zip(names, slots)
    ]
    moving = moves_rays(model)
    n = max(problem.n, 1)

    def assign(values: dict) -> None:
        for name, (part, key) in zip(names, slots):
            part.params[key] = values[name]

    def objective(values, step: int) -> float:
        if step == 1 or (moving and (step - 1) % retrace_every == 0):
            with dr.suspend_grad():
                assign(values())
            problem.trace(model)
        total = 0.0
        for chunk in problem.chunks:
            assign(values())  # a fresh graph per chunk: backward releases the previous one
            loss = -dr.sum(problem.chunk_log_likelihood(model, chunk)) / n
            # A loss that does not depend on the parameters (an effect that cannot act on these rays, e.g.
            # corner returns on analytic shapes, which have no corners) leaves them where they are.
            dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
            total += float(loss[0])
        if progress is not None:
            progress(step, steps)
        return total

    # A fit of ray-moving parameters gains in jumps at its re-traces: look back over one of them at least. Its
    # likelihood is sharp (a grazing ground return moves by r^2 / h per radian of pitch: 9 cm at 40 m for
    # 1e-4 rad), so its steps end at lr / 100: at lr / 10 a mounting error was left 1e-4 rad off, 0.37 nats/ray.
    window = window or (retrace_every + 5 if moving else 10)
    result = adam_fit(
        variables,
        objective,
        steps,
        lr=lr,
        schedule=fine_cosine_schedule if moving else cosine_schedule,
        tolerance=tolerance,
        window=window,
        min_steps=window + 2,
    )
    assign({name: mi.Float(aligned(result.values[name].astype(np.float32))) for name in names})
    make_opaque(parts)
    if moving:
        problem.trace(model)
    history = [-loss for step, loss, _ in result.history if step > 0]
    return PartsFit(
        history=history, parameters={f"{part.name}.{key}": np.asarray(part.params[key]) for part, key in slots}
    )


def score_log(scene, model, rays: LogRays, index: np.ndarray | None = None) -> np.ndarray:
    """(N,) scored per-ray log-likelihood of rays ``index`` of a log under ``model`` (a one-off score)."""
    return Problem.build(scene, rays, index).log_likelihood(model)


def mean_nll(values: np.ndarray) -> float:
    """Mean negative log-likelihood (nats per ray) of scored values; NaN when empty."""
    return float(-np.mean(values)) if len(values) else math.nan
