"""The one tracer: the elements met along each ray, stored compactly, only where a ray met one.

The likelihood traces rays once without gradients and rebuilds the segments with gradients as
often as it needs (every step of a fit). A full-width record (one lane per ray and round,
``max_segments`` rounds) would spend most of its lanes on rays that met nothing in that round; here
every round keeps only its *entries*, the rays that met an element in it:

* :class:`Round` holds, per entry, the ray's lane in the batch (``ray``), where the same ray sits in
  the previous round (``prev``; in round 0 its batch lane), whether the ray meets no further
  element (``last``), the element, the traced nominal range, incidence, point and normal; optionally
  the element's return distribution before effects (``cached``: mean, sigma, lo, hi), when nothing
  fitted moves rays or geometry so that it can be computed once;
* :func:`trace_rounds` traces a batch of rays round by round with Mitsuba, compacting the live rays
  after every round and stopping when none is left (the sampler,
  :meth:`~mi_lidar.core.sensor_model.SensorModel.simulate_rays`, walks the same rounds with
  :func:`next_hit` and draws as it goes);
* :func:`rounds_from_segments` builds the same structure from segments traced by another tracer
  (the grid ray march of planar logs, :mod:`mi_lidar.planar`);
* :class:`RayCache` stores the rounds of a whole part of a log ray by ray (the entries of ray ``i``
  are ``start[i] .. start[i] + count[i] - 1``, in round order) and cuts the :class:`Rounds` of any
  batch of its rays out of them with a few numpy operations.

The pass-through mixture is then a chain through the rounds
(:func:`mi_lidar.core.likelihood.mixture_log_likelihood`): entry ``j`` of round ``k`` reads the
running sums of its ray from the previous round's arrays at ``prev[j]``, so every array stays as
short as the round.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.rays import RayBatch

RESTART_OFFSET = 1e-4  # m: a ray continues this far past the element it passed through
MIN_RAY_LENGTH = 2.0**-10  # m (about 1 mm): the shortest direction vector handed to Mitsuba (see mitsuba_ray_length)
CACHED_FIELDS = ("mean", "sigma", "lo", "hi")  # return distribution before effects, m (then the corners)


def mitsuba_ray_length(ellipsoid_sizes: np.ndarray) -> float:
    """Length (m) of the direction vectors handed to Mitsuba, so that its ellipsoid test stays exact.

    Mitsuba 3.9.1's ``ellipsoids`` shape maps a ray to the element's unit-sphere frame
    (``d' = R^T d / (extent scale)``), moves its origin by ``dot(-o', d') / |d'|`` along ``d'`` and
    solves the quadratic there in float32. The moved origin is the point nearest the centre only when
    ``|d'| = 1``; otherwise it lies about ``(|d'| - 1) t'`` element radii away (``t'`` the distance
    in radii) and the discriminant, of order 1, loses about ``eps ((|d'| - 1) t')^2``. With unit
    directions a 2 cm element 10 m away was missed by 26 % of the rays aimed inside it, a 5 cm one
    60 m away by 19 % (float64 Mitsuba does the same). A length ``L`` no longer than the smallest
    ``extent x scale`` axis of the scene gives ``|d'| <= 1`` for every element, and the loss is at
    most ``eps (t / 4 L)^2`` (``t`` in m): with the power of two below a 2 cm element's 6 cm, 0.11 %
    of the rays aimed inside it 120 m away, those grazing its silhouette, are missed
    (tests/core/test_ellipsoid_precision.py). Mitsuba's distances are then in units of the length;
    :func:`next_hit` works with points only.

    Args:
        ellipsoid_sizes: (N, 3) ``extent x scale`` of every ellipsoid, m (empty: none).

    Returns:
        The largest power of two not above the smallest axis, clipped to ``[MIN_RAY_LENGTH, 1]``: 1
        in scenes without ellipsoids. A power of two scales directions exactly, so triangles are met
        at the same points as with unit directions, and a scene whose sizes are rounded (written to
        XML and read back) gets the same length.
    """
    sizes = np.abs(np.asarray(ellipsoid_sizes, np.float64))
    sizes = sizes[np.isfinite(sizes) & (sizes > 0)]  # a degenerate element must not set every ray's length
    if sizes.size == 0:
        return 1.0
    smallest = float(np.clip(np.min(sizes), MIN_RAY_LENGTH, 1.0))
    return float(2.0 ** np.floor(np.log2(smallest)))


def mitsuba_ray(start: mi.Point3f, direction: mi.Vector3f, length: float) -> mi.Ray3f:
    """The ray handed to Mitsuba from ``start`` along unit ``direction``: its direction is ``length`` m
    long (a scene's :func:`mitsuba_ray_length`, ``ElementTable.ray_length``), so ``ray(t)`` is a point
    and ``t * length`` the distance in metres."""
    return mi.Ray3f(start, direction * length)


def next_hit(
    scene, table, start: mi.Point3f, origin: mi.Point3f, direction: mi.Vector3f, max_range: float, active=True
):
    """The next element along each ray from ``start``, without its surface details: ``(pi, point, valid, element)``.

    ``pi`` is Mitsuba's preliminary intersection along :func:`mitsuba_ray` (primitive, shape and
    ``t`` in units of ``table.ray_length``: enough for the surface interaction later,
    ``pi.compute_surface_interaction(mitsuba_ray(start, direction, table.ray_length), ...)``); ``point`` is where
    the ray met the element (m; for an ellipsoid the entry of its chord, not Mitsuba's approximate
    one, which could lie before the element: the ray would meet it again); the ray continues from
    ``point + RESTART_OFFSET direction``.
    ``valid`` is False where the ray meets nothing within ``max_range`` (m, measured from ``origin``
    along ``direction``) and on inactive lanes (``active``: a mask or True). Rays are Lidar-ordered,
    so the query is flagged coherent.
    """
    ray = mitsuba_ray(start, direction, table.ray_length)
    pi = scene.ray_intersect_preliminary(ray, True, active)
    point = ray(pi.t)
    met = pi.is_valid()
    element = dr.select(met, table.element_of(pi), 0)
    if table.has_ellipsoids:  # Mitsuba's entry is approximate (2 cm for a 2 cm element at 120 m): take the chord's
        inside, entry = table.ellipsoid_entry(element, met, origin, direction)
        travelled = dr.dot(start - origin, direction)  # never step back behind the start
        point = dr.select(inside, origin + dr.maximum(entry, travelled) * direction, point)
    valid = met & (dr.dot(point - origin, direction) <= max_range)
    return pi, point, valid, dr.select(valid, element, 0)


def next_intersection(
    scene, table, start: mi.Point3f, origin: mi.Point3f, direction: mi.Vector3f, max_range: float, active=True
):
    """The next element along each ray from ``start`` with its surface interaction: ``(si, valid, element)``.

    :func:`next_hit` followed by the surface interaction (``mi.RayFlags.Minimal``: ``si.p``, ``si.n``)
    of the element met; ``valid`` and ``element`` as there.
    """
    pi, _, valid, element = next_hit(scene, table, start, origin, direction, max_range, active)
    si = pi.compute_surface_interaction(mitsuba_ray(start, direction, table.ray_length), mi.RayFlags.Minimal, active)
    return si, valid, element


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
        point, normal: traced intersection point (m) and shading normal (the tangent plane of
            shapes whose geometry the element table does not hold).
        cached: optional ``(mean, sigma, lo, hi)`` (m) of the element's return distribution before
            effects, computed once without gradients (``sigma`` is used for ellipsoids only; surfaces
            read theirs from the table so that it can be fitted), followed in scenes with triangles
            by the 3 corner offsets (m) and 3 corner weights (:func:`~mi_lidar.core.segment.corners`).
        log_density: optional log density (1/m) of the ray's measured range under the element's
            return distribution after effects, computed once (valid while only hit probabilities
            are fitted and no effect edits segments).
        drop: with ``log_density``, the probability that the element loses the beam (computed once too).
    """

    ray: mi.UInt32
    prev: mi.UInt32
    last: mi.Bool
    element: mi.UInt32
    nominal: mi.Float
    cos_incidence: mi.Float
    point: mi.Point3f
    normal: mi.Vector3f
    cached: tuple | None = None
    log_density: mi.Float | None = None
    drop: mi.Float | None = None

    @property
    def width(self) -> int:
        """Number of entries."""
        return dr.width(self.ray)

    def take(self, index: mi.UInt32) -> Round:
        """The entries at ``index`` (``prev`` still points into the previous round's entries)."""
        return Round(**{f.name: _take(getattr(self, f.name), index) for f in fields(self)})


def _take(array, index: mi.UInt32):
    """``array`` (a Dr.Jit array, a tuple of them, or None) at ``index``."""
    if array is None:
        return None
    if isinstance(array, tuple):
        return tuple(_take(a, index) for a in array)
    return dr.gather(type(array), array, index)


@dataclass
class Rounds:
    """The traced elements of a batch of rays, round by round.

    Attributes:
        width: rays in the batch (sub-rays when the model fans beams out, see :func:`trace_rounds`).
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


def traced_rays(model, rays: RayBatch) -> RayBatch:
    """The rays ``model`` traces for ``rays``: after its ray perturbations, fanned out into sub-rays
    when an effect spreads the beam (:meth:`~mi_lidar.core.sensor_model.SensorModel.fan_out`)."""
    rays = model.prepare_rays(rays)
    fan = model.fan_out(rays)
    return rays if fan is None else fan[1]


def trace_rounds(scene, table, model, rays: RayBatch) -> Rounds:
    """Trace up to ``model.max_segments`` elements along every ray, without gradients.

    Follows the sampler's rules (restart ``RESTART_OFFSET`` m past each element, nothing beyond
    ``max_range``). After every round only the rays that met an element are traced on; the trace
    stops when none is left. The rays traced are :func:`traced_rays` of the batch: with a
    footprint effect the rounds hold the ``m n`` sub-rays of the ``n`` beams.

    Args:
        scene: the loaded Mitsuba scene.
        table: its element table.
        model: the sensor model.
        rays: the batch (world frame).
    """
    rounds: list[Round] = []
    with dr.suspend_grad():
        rays = traced_rays(model, rays)
        n = rays.width
        origin, direction = mi.Point3f(dr.detach(rays.origin)), mi.Vector3f(dr.detach(rays.direction))
        start = mi.Point3f(origin)
        lanes = dr.arange(mi.UInt32, n)  # batch lane of each live ray
        none = dr.full(mi.Bool, True, n)
        for k in range(model.max_segments):
            # ---------------- Next element along every live ray ----------------
            pi, point, valid, element = next_hit(scene, table, start, origin, direction, model.max_range)
            si = pi.compute_surface_interaction(mitsuba_ray(start, direction, table.ray_length), mi.RayFlags.Minimal)
            nominal = dr.dot(si.p - origin, direction)
            cos_incidence = dr.abs(dr.dot(si.n, direction))
            dr.eval(valid, element, nominal, cos_incidence, si.p, si.n, point)
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
                    point=dr.gather(mi.Point3f, si.p, keep),
                    normal=dr.gather(mi.Vector3f, mi.Vector3f(si.n), keep),
                )
            )
            origin = dr.gather(mi.Point3f, origin, keep)
            direction = dr.gather(mi.Vector3f, direction, keep)
            start = dr.gather(mi.Point3f, point, keep) + RESTART_OFFSET * direction
            dr.eval(rounds[-1], origin, direction, start)
    return Rounds(width=n, none=none, rounds=rounds)


def rounds_from_segments(
    start: np.ndarray, element: np.ndarray, nominal: np.ndarray, cos_incidence: np.ndarray
) -> Rounds:
    """The :class:`Rounds` of rays whose elements another tracer found (CSR layout, numpy).

    Each entry's return distribution is cached as that of a surface at its nominal range (the
    element's own range sigma), so the likelihood needs no geometry: build the table with
    :meth:`~mi_lidar.core.elements.ElementTable.from_elements`.

    Args:
        start: (N + 1,) offsets: the entries of ray ``i`` are ``start[i] .. start[i + 1] - 1``, in
            order along the ray.
        element: (E,) element index of every entry (into the table the segments are built from).
        nominal: (E,) nominal range of every entry, m.
        cos_incidence: (E,) |cos| of the incidence of every entry (NaN where unknown).
    """
    count = np.diff(np.asarray(start, np.int64))
    r = mi.Float(aligned(np.asarray(nominal, np.float32)))
    size = dr.width(r)
    cache = RayCache(
        start=np.asarray(start[:-1], np.int64),
        count=count,
        element=mi.UInt32(aligned(np.asarray(element, np.uint32))),
        nominal=r,
        cos_incidence=mi.Float(aligned(np.asarray(cos_incidence, np.float32))),
        point=None,
        normal=None,
        cached=(r, dr.full(mi.Float, dr.nan, size), dr.full(mi.Float, -dr.inf, size), dr.full(mi.Float, dr.inf, size)),
    )
    return cache.select(np.arange(len(count)))


def cache_distributions(rounds: Rounds, table, model, rays: RayBatch, measured: mi.Float | None = None) -> Rounds:
    """``rounds`` with each entry's return distribution computed once (:attr:`Round.cached`).

    Valid while nothing fitted moves rays or geometry: the cached values are those of the current
    table geometry and of ``rays`` after the model's ray perturbations.

    Args:
        rounds, table, model, rays: the trace, the element table, the sensor model and the batch.
        measured: (B,) measured ranges (m); when given, the log density of each entry's measured
            range under the model's density after effects is cached too (:attr:`Round.log_density`).
    """
    out = []
    with dr.suspend_grad():
        rays = model.prepare_rays(rays)
        for r in rounds.rounds:
            sub = rays.take(r.ray)
            valid = dr.full(mi.Bool, True, r.width)
            if r.cached is None:
                seg = table.segment(r, valid, r.element, sub.origin, sub.direction, model.range_sigma)
            else:  # segments of another tracer come with their distributions
                seg = table.cached_segment(r, valid, model.range_sigma)
            cached = tuple(getattr(seg, f) for f in CACHED_FIELDS)
            if seg.corner_offset is not None:
                cached += tuple(seg.corner_offset) + tuple(seg.corner_weight)
            density = drop = None
            if measured is not None:
                seg = model.segment_law(seg, sub)
                drop, density = model.censor(
                    seg, model.density.log_prob(seg, dr.gather(mi.Float, measured, r.ray), sub), sub
                )
                drop = drop + dr.zeros(mi.Float, r.width)
            dr.eval(cached, density, drop)
            out.append(replace(r, cached=cached, log_density=density, drop=drop))
    return replace(rounds, rounds=out)


@dataclass
class RayCache:
    """The rounds of every ray of a part of a log, stored ray by ray.

    Attributes:
        start: (N,) index of each ray's first entry.
        count: (N,) entries of each ray (elements it met).
        element: (E,) global element index of every entry.
        nominal, cos_incidence: (E,) traced nominal range (m) and |cos| of the incidence.
        point, normal: (E,) traced points and normals (None for segments of another tracer).
        cached: optional ``(mean, sigma, lo, hi)`` arrays (E,) of :attr:`Round.cached`.
        log_density, drop: optional (E,) :attr:`Round.log_density` and :attr:`Round.drop`.
    """

    start: np.ndarray
    count: np.ndarray
    element: mi.UInt32
    nominal: mi.Float
    cos_incidence: mi.Float
    point: mi.Point3f | None
    normal: mi.Vector3f | None
    cached: tuple | None
    log_density: mi.Float | None = None
    drop: mi.Float | None = None

    @classmethod
    def from_rounds(cls, rounds: Rounds) -> RayCache:
        """Reorder the rounds of a batch (round by round) into the ray-by-ray layout."""
        rays = [np.asarray(r.ray, np.int64) for r in rounds.rounds]
        count = np.zeros(rounds.width, np.int64)
        for lanes in rays:
            count[lanes] += 1  # a ray has at most one entry per round
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        size = max(int(count.sum()), 1)
        first = rounds.rounds[0] if rounds.rounds else None
        element = dr.zeros(mi.UInt32, size)
        nominal, cos_incidence = dr.zeros(mi.Float, size), dr.zeros(mi.Float, size)
        point, normal = dr.zeros(mi.Point3f, size), dr.zeros(mi.Vector3f, size)
        cached = tuple(dr.zeros(mi.Float, size) for _ in first.cached) if first and first.cached else None
        with_density = first is not None and first.log_density is not None
        density = dr.zeros(mi.Float, size) if with_density else None
        drop = dr.zeros(mi.Float, size) if with_density else None
        for k, (r, lanes) in enumerate(zip(rounds.rounds, rays)):
            slot = mi.UInt32(aligned((start[lanes] + k).astype(np.uint32)))
            for target, value in (
                (element, r.element),
                (nominal, r.nominal),
                (cos_incidence, r.cos_incidence),
                (point, r.point),
                (normal, r.normal),
            ):
                if value is not None:  # segments of another tracer have no traced points
                    dr.scatter(target, value, slot)
            for target, value in zip(cached or (), r.cached or ()):
                dr.scatter(target, value, slot)
            if with_density:
                dr.scatter(density, r.log_density, slot)
                dr.scatter(drop, r.drop, slot)
            dr.eval(element, nominal, cos_incidence, point, normal, cached, density, drop)
        return cls(
            start=start,
            count=count,
            element=element,
            nominal=nominal,
            cos_incidence=cos_incidence,
            point=point,
            normal=normal,
            cached=cached,
            log_density=density,
            drop=drop,
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
            # positions among the previous round's entries (round 0: the batch lanes)
            prev = np.flatnonzero(count > 0) if k == 0 else np.flatnonzero(count[lanes] > k)
            lanes = lanes[prev]
            entry = mi.UInt32(aligned((start[lanes] + k).astype(np.uint32)))
            rounds.append(
                Round(
                    ray=mi.UInt32(aligned(lanes.astype(np.uint32))),
                    prev=mi.UInt32(aligned(prev.astype(np.uint32))),
                    last=mi.Bool(aligned(count[lanes] == k + 1)),
                    element=_take(self.element, entry),
                    nominal=_take(self.nominal, entry),
                    cos_incidence=_take(self.cos_incidence, entry),
                    point=_take(self.point, entry),
                    normal=_take(self.normal, entry),
                    cached=_take(self.cached, entry),
                    log_density=_take(self.log_density, entry),
                    drop=_take(self.drop, entry),
                )
            )
        return Rounds(width=len(position), none=mi.Bool(aligned(count == 0)), rounds=rounds)


@dataclass
class CachedBatch:
    """A batch of a :class:`RayCache`'s rays, read ray by ray (one lane per ray).

    Entry ``k`` of lane ``i`` is ``start[i] + k`` for ``k < count[i]``. With the return
    distributions cached, the whole mixture of a batch is one kernel of ``cache.max_count`` unrolled
    rounds (:func:`mi_lidar.core.likelihood.mixture_log_likelihood`), whose code is the same for
    every batch.

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
