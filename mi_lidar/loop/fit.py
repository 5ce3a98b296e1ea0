"""Fit effect parameters by maximum likelihood (Adam on the pass-through mixture).

A small, self-contained fitter for the loop: it fits the parameters of chosen effects of a
:class:`~mi_lidar.core.sensor_model.SensorModel` to measured rays with :class:`mi.ad.Adam`, and scores
rays with the pass-through mixture of :meth:`SensorModel.log_likelihood`. Each parameter is
optimised in units of its scale (``Effect.fit_scales[name]``, default 0.1) and clipped to its
:class:`ParamSpec` bounds after every step. Parameters listed in ``Effect.fit_exclude`` stay fixed;
parameters listed in ``Effect.per_label`` (and per-beam parameters) are widened to one value per
label (beam) first.

Speed. A split is traced once (:meth:`Problem.trace`) into *compact rounds*: round ``k`` holds
only the rays that meet a ``k``-th element, with the element's segment before effects computed
once and stored. The likelihood then evaluates one small kernel per round over those lanes (the
kernel of rounds ``k >= 1`` is the same code, compiled once), instead of one kernel holding every
round at full width with both the triangle and the ellipsoid geometry. Effect parameters enter
kernels as opaque values, so one compiled kernel serves every step of a fit and every candidate
with the same code. Only effects that move rays (:meth:`Effect.perturb_rays`) recompute the
geometry in the kernel, from the traced tangent planes and ellipsoids (:class:`PlaneTable`).

Scoring floor. A measured return that the model cannot produce at all (no element along the ray
near the measured range, say) has log-likelihood -inf; one such ray would make a mean NLL
infinite and hide every other difference between models. Scores are therefore floored at
:data:`LL_FLOOR` nats per ray: such a ray costs 30 nats, about the NLL of a return 7.7 sigma away
from its element. Fitting floors at the lower :data:`FIT_FLOOR`, so that such rays keep pulling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.effects.base import Effect
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.rays import LogRays, RayBatch
from mi_lidar.core.segment import SURFACE, Segment
from mi_lidar.core.sensor_model import SensorModel, mixture_step

LL_FLOOR = -30.0  # nats: per-ray log-likelihood floor of scoring (see the module docstring)
# nats: the fitting loss's floor, lower than the scoring one so that rays far from their element
# (a beam tilted onto another surface) still pull the parameters back (a 45 sigma residual).
FIT_FLOOR = -1000.0
DEFAULT_SCALE = 0.1
# Adam step in units of each parameter's scale; with the cosine decay to a tenth, 100 steps can
# move a parameter about 15 scales from its start and end with steps of 0.03 scales.
LEARNING_RATE = 0.3
BATCH = 1 << 18  # rays scored at once
SEGMENT_FIELDS = ("nominal", "p", "mean", "sigma", "lo", "hi", "cos_incidence", "element", "shape", "label", "kind")


class PlaneTable(ElementTable):
    """An element table whose surface ranges follow the traced tangent plane.

    Surface ranges become ``t = dot(p - o, n) / dot(d, n)`` with the traced point ``p`` and normal
    ``n`` held fixed, so that gradients with respect to the ray origin ``o`` and direction ``d``
    (beam offsets, extrinsics, motion) are those of the surface, not of the fixed traced point.
    """

    @classmethod
    def of(cls, table: ElementTable) -> PlaneTable:
        """Wrap an existing table (arrays shared)."""
        return cls(**{k: getattr(table, k) for k in table.__dataclass_fields__})

    def segment(self, si, valid, element, origin, direction, default_sigma: float):
        seg = super().segment(si, valid, element, origin, direction, default_sigma)
        n = dr.detach(si.n)
        denom = dr.dot(direction, n)
        safe = dr.select(dr.abs(denom) > 1e-6, denom, 1e-6)
        t = dr.dot(dr.detach(si.p) - origin, n) / safe
        surface = seg.kind == SURFACE
        return seg.with_(
            nominal=dr.select(surface, t, seg.nominal), mean=dr.select(surface, seg.mean - seg.nominal + t, seg.mean)
        )


def widen(effect: Effect, n_beams: int, n_labels: int) -> Effect:
    """Give per-beam parameters ``n_beams`` values and per-label ones ``n_labels`` (in place)."""
    for key, spec in effect.specs.items():
        size = n_beams if spec.per_beam else n_labels if key in getattr(effect, "per_label", ()) else 1
        values = np.asarray(effect.params[key])
        if values.size == 1 and size > 1:
            effect.params[key] = mi.Float(aligned(np.full(size, values[0], np.float32)))
    return effect


def fitted_names(effect: Effect) -> list[str]:
    """Names of the parameters of ``effect`` that fitting changes."""
    return [k for k in effect.specs if k not in getattr(effect, "fit_exclude", ())]


def n_parameters(effects: list[Effect]) -> int:
    """Number of scalar fitted parameters of ``effects``."""
    return int(sum(dr.width(e.params[k]) for e in effects for k in fitted_names(e)))


def make_opaque(effects: list[Effect]) -> None:
    """Turn the effects' parameters into opaque kernel inputs (in place).

    A width-1 array built from a Python or numpy value is a literal that Dr.Jit bakes into the
    kernel, so every new value would compile a new kernel; opaque values are read from memory.
    """
    for effect in effects:
        for key, value in effect.params.items():
            array = mi.Float(aligned(np.asarray(dr.detach(value), dtype=np.float32)))
            dr.make_opaque(array)
            effect.params[key] = array


def moves_rays(model: SensorModel) -> bool:
    """True when an effect of ``model`` edits rays before tracing (angle offsets, extrinsics, motion, footprint)."""
    return any(
        type(e).perturb_rays is not Effect.perturb_rays or type(e).footprint is not Effect.footprint
        for e in model.effects
    )


def _ray_key(model: SensorModel) -> tuple:
    """Identity of the rays ``model`` traces: its ray-moving effects and their parameter values."""
    return tuple(
        (e.name, tuple(np.asarray(dr.detach(v)).tobytes() for v in e.params.values()))
        for e in model.effects
        if type(e).perturb_rays is not Effect.perturb_rays or type(e).footprint is not Effect.footprint
    )


@dataclass
class Round:
    """The rays of a chunk that meet a ``k``-th element, and that element (compact lanes).

    Attributes:
        lanes: (M,) chunk lanes (rays) of this round, ascending.
        prev: (M,) position of each lane in the previous round (round 0: equal to ``lanes``).
        last: (M,) True where the ray meets no further element.
        base: the element's segment before effects (fields evaluated, no gradients), or None when
            the rays move and the geometry is recomputed from ``si``.
        si: the traced intersections of the lanes (only when the rays move).
        element: (M,) global element index.
    """

    lanes: mi.UInt32
    prev: mi.UInt32
    last: mi.Bool
    base: Segment | None
    si: object
    element: mi.UInt32


@dataclass
class Chunk:
    """Up to :data:`BATCH` rays of a split, traced into compact rounds.

    Attributes:
        rays: the measured rays (before the model's ray perturbations).
        z: (N,) measured range, m (0 for a miss).
        hit: (N,) True where the sensor reported a return.
        met: (N,) True where the ray meets at least one element.
        rounds: the compact rounds, first element first.
        records: the full-width records of :meth:`SensorModel.trace_segments`, kept instead of
            rounds when an effect fans beams out into sub-rays (scored by the core likelihood).
    """

    rays: RayBatch
    z: mi.Float
    hit: mi.Bool
    met: mi.Bool
    rounds: list[Round]
    records: list | None = None


def trace_chunk(model: SensorModel, scene, table: ElementTable, rays: RayBatch, z: mi.Float, hit: mi.Bool) -> Chunk:
    """Trace ``rays`` under ``model`` and keep, per round, only the lanes that met an element."""
    records = model.trace_segments(scene, table, rays)
    if any(type(e).footprint is not Effect.footprint for e in model.effects):
        return Chunk(
            rays=rays,
            z=dr.select(hit, z, 0.0),
            hit=hit,
            met=dr.full(mi.Bool, True, rays.width),
            rounds=[],
            records=records,
        )
    moving = moves_rays(model)
    with dr.suspend_grad():
        prepared = model.prepare_rays(rays)
        valid = np.stack([np.asarray(r["valid"]) for r in records]) if records else np.zeros((0, rays.width), bool)
        count = np.cumprod(valid, axis=0).sum(axis=0)  # elements met in a row from the first
        rounds, previous = [], None
        for k, record in enumerate(records):
            lanes_np = np.flatnonzero(count > k).astype(np.uint32)
            if lanes_np.size == 0:
                break
            prev_np = lanes_np if previous is None else np.searchsorted(previous, lanes_np).astype(np.uint32)
            lanes = mi.UInt32(aligned(lanes_np))
            si = dr.gather(type(record["si"]), record["si"], lanes)
            element = dr.gather(mi.UInt32, record["element"], lanes)
            base = None
            if not moving:
                sub = prepared.take(lanes)
                seg = table.segment(
                    si, dr.full(mi.Bool, True, lanes_np.size), element, sub.origin, sub.direction, model.range_sigma
                )
                base = seg
                dr.eval(*(getattr(base, f) for f in ("valid",) + SEGMENT_FIELDS))
                si = None
            else:
                dr.eval(si.p, si.n, element)
            rounds.append(
                Round(
                    lanes=lanes,
                    prev=mi.UInt32(aligned(prev_np)),
                    last=mi.Bool(aligned(count[lanes_np] == k + 1)),
                    base=base,
                    si=si,
                    element=element,
                )
            )
            previous = lanes_np
    return Chunk(rays=rays, z=dr.select(hit, z, 0.0), hit=hit, met=mi.Bool(aligned(count > 0)), rounds=rounds)


def chunk_log_likelihood(model: SensorModel, table: ElementTable, chunk: Chunk, resolution: float = 0.0) -> mi.Float:
    """Per-ray log-likelihood (nats) of a traced chunk under ``model``; differentiable in effect parameters.

    Equal to :meth:`SensorModel.log_likelihood` on the same rays: the virtual elements at full
    width, then one compact round after the other, each lane's mixture carried over by a gather.
    """
    if chunk.records is not None:
        return model.log_likelihood(table, chunk.rays, chunk.records, chunk.z, chunk.hit, resolution)
    rays = model.prepare_rays(chunk.rays)
    n = chunk.rays.width
    log_mix, log_pass = dr.full(mi.Float, -dr.inf, n), dr.zeros(mi.Float, n)
    for seg in model.virtual_segments(rays):
        log_mix, log_pass = mixture_step(log_mix, log_pass, model.likelihood_segment(seg, rays), chunk.z)
    ll = dr.select(chunk.met, 0.0, dr.select(chunk.hit, log_mix, log_pass))
    for r in chunk.rounds:
        sub = rays.take(r.lanes)
        z = dr.gather(mi.Float, chunk.z, r.lanes)
        hit = dr.gather(mi.Bool, chunk.hit, r.lanes)
        log_mix, log_pass = dr.gather(mi.Float, log_mix, r.prev), dr.gather(mi.Float, log_pass, r.prev)
        seg = (
            r.base
            if r.base is not None
            else table.segment(
                r.si, dr.full(mi.Bool, True, dr.width(r.lanes)), r.element, sub.origin, sub.direction, model.range_sigma
            )
        )
        seg = model.likelihood_segment(model.apply_effects(seg, sub), sub)
        log_mix, log_pass = mixture_step(log_mix, log_pass, seg, z)
        dr.scatter_add(ll, dr.select(hit, log_mix, log_pass), r.lanes, r.last)
    if resolution > 0:
        ll = dr.select(chunk.hit, ll + math.log(resolution), ll)
    return ll


@dataclass
class Problem:
    """Measured rays of one split, traced once, ready to score and fit.

    Attributes:
        scene: loaded Mitsuba scene.
        table: its element table (a :class:`PlaneTable`).
        rays: the log's rays.
        index: (N,) indices (into ``rays``) of the rays of this split.
        resolution: range bin (m) of the discretized score; 0 scores densities.
        chunks: the traced chunks (see :meth:`trace`).
    """

    scene: object
    table: ElementTable
    rays: LogRays
    index: np.ndarray
    resolution: float = 0.0
    chunks: list = field(default_factory=list, repr=False)
    _traced: tuple | None = field(default=None, repr=False)

    @classmethod
    def build(cls, scene, rays: LogRays, index: np.ndarray, resolution: float = 0.0) -> Problem:
        return cls(
            scene=scene,
            table=PlaneTable.of(ElementTable.from_scene(scene)),
            rays=rays,
            index=np.asarray(index),
            resolution=resolution,
        )

    def trace(self, model: SensorModel) -> None:
        """Trace every chunk of the split under ``model`` (its ray perturbations included).

        Tracing is skipped when the rays ``model`` traces are those of the last trace (the same
        ray-moving effects with the same values), as they are for every effect that only edits
        segments.
        """
        key = (_ray_key(model), model.max_range, model.max_segments, model.range_sigma)
        if self._traced == key and self.chunks:
            return
        self.chunks = []
        for first in range(0, self.index.size, BATCH):
            batch, measured, hit = self.rays.batch(self.index[first : first + BATCH])
            self.chunks.append(trace_chunk(model, self.scene, self.table, batch, measured, hit))
        self._traced = key

    def log_likelihood(self, model: SensorModel, floor: float | None = LL_FLOOR) -> np.ndarray:
        """(N,) per-ray log-likelihood (nats) under ``model``, floored at ``floor`` (None: not floored)."""
        self.trace(model)
        out = []
        with dr.suspend_grad():
            for chunk in self.chunks:
                ll = np.asarray(chunk_log_likelihood(model, self.table, chunk, self.resolution), dtype=np.float64)
                out.append(ll if floor is None else np.maximum(ll, floor))
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


def fit_effects(
    model: SensorModel,
    problem: Problem,
    effects: list[Effect] | None = None,
    steps: int = 150,
    lr: float = LEARNING_RATE,
    retrace_every: int = 10,
    progress=None,
) -> FitResult:
    """Maximise the mean log-likelihood of ``problem``'s rays over effect parameters.

    Args:
        model: sensor model holding the effects (changed in place: fitted values are written
            into the effects' ``params``, as opaque arrays).
        problem: the measured rays (traced on demand).
        effects: effects to fit (default: all of ``model.effects``).
        steps: Adam steps.
        lr: learning rate in units of each parameter's scale (decays to lr/10, cosine).
        retrace_every: steps between re-traces when an effect perturbs rays.
        progress: optional callable ``progress(step, steps)``.

    Returns:
        The loss history and the fitted parameters: those of the lowest loss seen (the loss is
        over every ray, so a refit never ends worse than its start).
    """
    effects = model.effects if effects is None else effects
    make_opaque(model.effects)
    slots = [(e, k) for e in effects for k in fitted_names(e)]
    if not slots:
        return FitResult(history=[], parameters={})
    moving = moves_rays(model)
    start = {(id(e), k): e.params[k] for e, k in slots}
    scales = [dr.opaque(mi.Float, getattr(e, "fit_scales", {}).get(k, DEFAULT_SCALE)) for e, k in slots]
    opt = mi.ad.Adam(lr=lr)
    for i, (e, k) in enumerate(slots):
        opt[f"{i}"] = dr.zeros(mi.Float, dr.width(e.params[k]))

    bounds = [(max(e.specs[k].fit_bound, -1e30), min(e.specs[k].upper, 1e30)) for e, k in slots]

    def assign():
        for i, (e, k) in enumerate(slots):
            value = start[(id(e), k)] + scales[i] * opt[f"{i}"]
            # straight-through clip: the value is kept in bounds, its gradient is the one at the bound
            e.params[k] = value + dr.detach(dr.clip(value, *bounds[i]) - value)

    def project():
        """Move the optimizer's variables back into the bounds (projected gradient steps)."""
        for i, (e, k) in enumerate(slots):
            base = start[(id(e), k)]
            inside = dr.clip(dr.detach(base + scales[i] * opt[f"{i}"]), *bounds[i])
            opt[f"{i}"] = (inside - dr.detach(base)) / scales[i]

    history = []
    best = (math.inf, None)  # lowest loss seen and the optimizer's variables it was measured at
    n = max(problem.index.size, 1)
    for step in range(steps):
        if step == 0 or (moving and step % retrace_every == 0):
            with dr.suspend_grad():
                assign()
            problem.trace(model)
        opt.set_learning_rate(lr * (0.1 + 0.45 * (1 + math.cos(math.pi * step / steps))))
        total = 0.0
        for chunk in problem.chunks:
            assign()  # a fresh graph per chunk: backward releases the previous one
            ll = chunk_log_likelihood(model, problem.table, chunk, problem.resolution)
            loss = -dr.sum(dr.maximum(ll, FIT_FLOOR)) / n
            dr.backward(loss)
            total += float(loss[0])
        if total < best[0]:
            best = (total, [np.array(opt[f"{i}"]) for i in range(len(slots))])
        opt.step()
        project()
        history.append(-total)
        if progress is not None:
            progress(step + 1, steps)
    for i, values in enumerate(best[1]):
        opt[f"{i}"] = mi.Float(aligned(values))
    with dr.suspend_grad():
        assign()
    make_opaque(effects)
    if moving:
        problem.trace(model)
    return FitResult(history=history, parameters={f"{e.name}.{k}": np.asarray(e.params[k]) for e, k in slots})
