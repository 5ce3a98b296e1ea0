"""Compact trace records: the elements met along each ray, stored only where a ray met one.

Calibration traces rays once without gradients and rebuilds the segments with gradients at every
step. A full-width record (one lane per ray and round, ``max_segments`` rounds) spends most of its
lanes on rays that met nothing in that round; here every round keeps only its *entries*, the rays
that met an element in it:

* :class:`Round` holds, per entry, the ray's lane in the batch (``ray``), where the same ray sits in
  the previous round (``prev``; in round 0 its batch lane), whether the ray meets no further
  element (``last``), the element and the traced nominal range and incidence; optionally the
  element's return distribution before effects (``cached``: mean, sigma, lo, hi), when nothing
  fitted moves rays or geometry so that it can be computed once;
* :func:`trace_rounds` traces a batch of rays round by round, compacting the live rays after every
  round and stopping when none is left;
* :class:`RayCache` stores the rounds of a whole part of a log ray by ray (the entries of ray
  ``i`` are ``start[i] .. start[i] + count[i] - 1``, in round order) and cuts the :class:`Rounds`
  of any batch of its rays out of them with a few numpy operations.

The pass-through mixture is then a chain through the rounds
(:func:`mi_lidar.calibration.likelihood.mixture_log_likelihood`): entry ``j`` of round ``k``
reads the running log pass probability and log mixture of its ray from the previous round's
arrays at ``prev[j]``, so every array stays as short as the round.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import log_density
from mi_lidar.core.sensor_model import RESTART_OFFSET, SensorModel

CACHED_FIELDS = ("mean", "sigma", "lo", "hi")  # return distribution before effects, m


@dataclass
class Round:
    """The entries of one round: rays that met an element in it (all fields have one lane per entry).

    Attributes:
        ray: lane of the entry's ray in the batch.
        prev: index of the same ray among the previous round's entries (round 0: its batch lane).
        last: the ray meets no further element.
        element: global element index.
        nominal: traced nominal range, m.
        cos_incidence: traced |cos| of the incidence angle.
        cached: optional ``(mean, sigma, lo, hi)`` (m) of the element's return distribution before
            effects, computed once without gradients (``sigma`` is used for ellipsoids only; surfaces
            read theirs from the table so that it can be fitted).
        log_density: optional log density (1/m) of the ray's measured range under the element's
            return distribution after effects, computed once (valid while only hit probabilities
            are fitted and no effect edits segments).
    """

    ray: mi.UInt32
    prev: mi.UInt32
    last: mi.Bool
    element: mi.UInt32
    nominal: mi.Float
    cos_incidence: mi.Float
    cached: tuple | None = None
    log_density: mi.Float | None = None

    @property
    def width(self) -> int:
        """Number of entries."""
        return dr.width(self.ray)


@dataclass
class Rounds:
    """The traced elements of a batch of rays, round by round.

    Attributes:
        width: rays in the batch.
        none: (width,) True for rays that met no element.
        rounds: the non-empty rounds, in order along the rays.
    """

    width: int
    none: mi.Bool
    rounds: list

    @property
    def entries(self) -> int:
        """Total number of (ray, element) entries."""
        return sum(r.width for r in self.rounds)


def trace_rounds(scene, table, model: SensorModel, rays: RayBatch) -> Rounds:
    """Trace up to ``model.max_segments`` elements along every ray, without gradients.

    Follows the sampler's rules (restart ``RESTART_OFFSET`` m past each element, nothing beyond
    ``max_range``). After every round only the rays that met an element are traced on; the trace
    stops when none is left.

    Args:
        scene: the loaded Mitsuba scene.
        table: its element table.
        model: the sensor model (its effects' ray perturbations are applied first).
        rays: the batch (world frame).
    """
    n = rays.width
    rounds = []
    with dr.suspend_grad():
        rays = model.prepare_rays(rays)
        origin, direction = mi.Point3f(dr.detach(rays.origin)), mi.Vector3f(dr.detach(rays.direction))
        start = mi.Point3f(origin)
        lanes = dr.arange(mi.UInt32, n)  # batch lane of each live ray
        none = dr.full(mi.Bool, True, n)
        for k in range(model.max_segments):
            # ---------------- Next element along every live ray ----------------
            si = scene.ray_intersect(mi.Ray3f(start, direction), mi.RayFlags.Minimal, True)
            nominal = dr.dot(si.p - origin, direction)
            valid = si.is_valid() & (nominal <= model.max_range)
            element = table.element_of(si)
            cos_incidence = dr.abs(dr.dot(si.n, direction))
            dr.eval(valid, element, nominal, cos_incidence, si.p)
            if k == 0:
                none = ~valid
            else:
                rounds[-1].last = ~valid  # the live rays are exactly the previous round's entries
            keep = dr.compress(valid)  # positions among the live rays
            if dr.width(keep) == 0:
                break
            # ---------------- Keep the entries, continue past them ----------------
            lanes = dr.gather(mi.UInt32, lanes, keep)
            rounds.append(
                Round(
                    ray=lanes,
                    prev=keep,
                    last=dr.full(mi.Bool, True, dr.width(keep)),
                    element=dr.gather(mi.UInt32, element, keep),
                    nominal=dr.gather(mi.Float, nominal, keep),
                    cos_incidence=dr.gather(mi.Float, cos_incidence, keep),
                )
            )
            origin = dr.gather(mi.Point3f, origin, keep)
            direction = dr.gather(mi.Vector3f, direction, keep)
            start = dr.gather(mi.Point3f, si.p, keep) + RESTART_OFFSET * direction
            dr.eval(rounds[-1], origin, direction, start)
    return Rounds(width=n, none=none, rounds=rounds)


def cache_distributions(
    rounds: Rounds, table, model: SensorModel, rays: RayBatch, measured: mi.Float | None = None
) -> Rounds:
    """``rounds`` with each entry's return distribution computed once (:attr:`Round.cached`).

    Valid while nothing fitted moves rays or geometry: the cached values are those of the current
    table geometry and of ``rays`` after the model's ray perturbations.

    Args:
        rounds, table, model, rays: the trace, the element table, the sensor model and the batch.
        measured: (B,) measured ranges (m); when given, the log density of each entry's measured
            range after effects is cached too (:attr:`Round.log_density`).
    """
    out = []
    with dr.suspend_grad():
        rays = model.prepare_rays(rays)
        for r in rounds.rounds:
            sub = rays.take(r.ray)
            seg = table.segment(
                r, dr.full(mi.Bool, True, r.width), r.element, sub.origin, sub.direction, model.range_sigma
            )
            cached = tuple(getattr(seg, f) for f in CACHED_FIELDS)
            density = None
            if measured is not None:
                seg = model.likelihood_segment(model.apply_effects(seg, sub), sub)
                density = log_density(seg, dr.gather(mi.Float, measured, r.ray))
            dr.eval(cached, density)
            out.append(replace(r, cached=cached, log_density=density))
    return replace(rounds, rounds=out)


@dataclass
class RayCache:
    """The rounds of every ray of a part of a log, stored ray by ray.

    Attributes:
        start: (N,) index of each ray's first entry.
        count: (N,) entries of each ray (elements it met).
        element: (E,) global element index of every entry.
        nominal, cos_incidence: (E,) traced nominal range (m) and |cos| of the incidence.
        cached: optional ``(mean, sigma, lo, hi)`` arrays (E,) of :attr:`Round.cached`.
        log_density: optional (E,) :attr:`Round.log_density`.
    """

    start: np.ndarray
    count: np.ndarray
    element: mi.UInt32
    nominal: mi.Float
    cos_incidence: mi.Float
    cached: tuple | None
    log_density: mi.Float | None = None

    @classmethod
    def from_rounds(cls, rounds: Rounds) -> RayCache:
        """Reorder the rounds of a batch (round by round) into the ray-by-ray layout."""
        rays = [np.asarray(r.ray, np.int64) for r in rounds.rounds]
        count = np.zeros(rounds.width, np.int64)
        for lanes in rays:
            count[lanes] += 1  # a ray has at most one entry per round
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        total = int(count.sum())
        with_cache = bool(rounds.rounds) and rounds.rounds[0].cached is not None
        element = dr.zeros(mi.UInt32, max(total, 1))
        nominal, cos_incidence = dr.zeros(mi.Float, max(total, 1)), dr.zeros(mi.Float, max(total, 1))
        cached = tuple(dr.zeros(mi.Float, max(total, 1)) for _ in CACHED_FIELDS) if with_cache else None
        with_density = bool(rounds.rounds) and rounds.rounds[0].log_density is not None
        density = dr.zeros(mi.Float, max(total, 1)) if with_density else None
        for k, (r, lanes) in enumerate(zip(rounds.rounds, rays)):
            slot = mi.UInt32(aligned((start[lanes] + k).astype(np.uint32)))
            dr.scatter(element, r.element, slot)
            dr.scatter(nominal, r.nominal, slot)
            dr.scatter(cos_incidence, r.cos_incidence, slot)
            for target, value in zip(cached or (), r.cached or ()):
                dr.scatter(target, value, slot)
            if with_density:
                dr.scatter(density, r.log_density, slot)
            dr.eval(element, nominal, cos_incidence, cached, density)
        return cls(
            start=start,
            count=count,
            element=element,
            nominal=nominal,
            cos_incidence=cos_incidence,
            cached=cached,
            log_density=density,
        )

    @property
    def n(self) -> int:
        """Number of rays."""
        return len(self.count)

    @property
    def max_count(self) -> int:
        """Most entries of any ray."""
        return int(self.count.max(initial=0))

    def batch(self, position: np.ndarray) -> CachedBatch:
        """The rays at ``position`` (batch lane ``i`` = ray ``position[i]``, repeats allowed), ray by ray."""
        position = np.asarray(position, np.int64)
        return CachedBatch(
            cache=self,
            start=mi.UInt32(aligned(self.start[position].astype(np.uint32))),
            count=mi.UInt32(aligned(self.count[position].astype(np.uint32))),
            position=position,
        )

    def select(self, position: np.ndarray) -> Rounds:
        """The :class:`Rounds` of the rays at ``position`` (batch lane ``i`` = ray ``position[i]``).

        Args:
            position: (B,) indices of rays of this cache (repeats allowed).
        """
        position = np.asarray(position, np.int64)
        count, start = self.count[position], self.start[position]
        lanes = np.arange(len(position))
        rounds = []
        for k in range(int(count.max(initial=0))):
            if k == 0:
                prev = np.flatnonzero(count > 0)
            else:
                prev = np.flatnonzero(count[lanes] > k)  # positions among the previous round's entries
            lanes = lanes[prev]
            entry = mi.UInt32(aligned((start[lanes] + k).astype(np.uint32)))
            gather = lambda array, entry=entry: dr.gather(type(array), array, entry)
            rounds.append(
                Round(
                    ray=mi.UInt32(aligned(lanes.astype(np.uint32))),
                    prev=mi.UInt32(aligned(prev.astype(np.uint32))),
                    last=mi.Bool(aligned(count[lanes] == k + 1)),
                    element=gather(self.element),
                    nominal=gather(self.nominal),
                    cos_incidence=gather(self.cos_incidence),
                    cached=None if self.cached is None else tuple(gather(a) for a in self.cached),
                    log_density=None if self.log_density is None else gather(self.log_density),
                )
            )
        return Rounds(width=len(position), none=mi.Bool(aligned(count == 0)), rounds=rounds)


@dataclass
class CachedBatch:
    """A batch of a :class:`RayCache`'s rays, read ray by ray (one lane per ray).

    Entry ``k`` of lane ``i`` is ``start[i] + k`` for ``k < count[i]``. With the return
    distributions cached, the whole mixture of a batch is one kernel of ``cache.max_count``
    unrolled rounds (:func:`mi_lidar.calibration.likelihood.mixture_log_likelihood`), whose code
    is the same for every batch.

    Attributes:
        cache: the cache.
        start, count: (B,) first entry and number of entries of each lane's ray.
        position: (B,) the rays' indices in the cache.
    """

    cache: RayCache
    start: mi.UInt32
    count: mi.UInt32
    position: np.ndarray

    @property
    def width(self) -> int:
        """Number of rays."""
        return len(self.position)

    def rounds(self) -> Rounds:
        """The same rays as compact :class:`Rounds`."""
        return self.cache.select(self.position)
