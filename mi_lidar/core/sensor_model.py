"""The one simulation core: first return through permeable elements, and its likelihood.

Both the ``lidar`` integrator (``mi.render`` of an XML scene) and :func:`mi_lidar.simulate`
call :meth:`SensorModel.simulate_rays`. Along each ray the elements ``k = 1..K`` are met in
order; each returns the beam with probability ``p_k`` (a Bernoulli draw) and otherwise lets it
pass. So the return comes from element ``k`` with probability
``P_k = p_k prod_{j<k} (1 - p_j)`` and the ray misses with ``prod_k (1 - p_k)``.
:meth:`SensorModel.log_likelihood` evaluates that mixture for measured ranges.

Randomness is counter-based (a TEA hash of seed, ray id, segment and stream), so a ray's draws
do not depend on which other rays are traced with it: the same seed gives the same scan on both
paths, and different seeds give independent scans.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, SubRayMoments
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment, log_density, sample_range

RESTART_OFFSET = 1e-4  # m: a ray continues this far past the element it passed through
NO_ELEMENT = 0xFFFFFFFF
VIRTUAL_SEGMENT = 1000  # random-stream segment index of the first virtual element
CHANNELS = ("range", "hit", "element_id", "shape_id", "label", "cos_incidence", "nominal_range", "segments")


def uniform(seed: int, ray_id: mi.UInt32, segment: int, stream: int) -> mi.Float:
    """Counter-based uniform numbers in [0, 1): one per lane, keyed by (seed, ray, segment, stream)."""
    key = (int(seed) * 0x9E3779B1 + segment * 0x85EBCA77 + stream * 0xC2B2AE3D) & 0xFFFFFFFF
    # An opaque key is a kernel input, not a constant: new seeds and rounds reuse compiled kernels.
    return mi.sample_tea_float32(ray_id, dr.opaque(mi.UInt32, key), 8)


def mixture_step(log_mix: mi.Float, log_pass: mi.Float, seg: Segment, z: mi.Float) -> tuple[mi.Float, mi.Float]:
    """Add the next element along each ray to the pass-through mixture.

    Args:
        log_mix: ``log sum_{j<k} P_j f_j(z)`` over the elements met so far (nats; -inf for none).
        log_pass: ``log prod_{j<k} (1 - p_j)``, the log-probability of passing them all (nats).
        seg: element ``k`` (lanes where ``seg.valid`` is False leave both sums unchanged).
        z: measured ranges (m).

    Returns:
        The updated ``(log_mix, log_pass)``, summed in log space without overflow.
    """
    p = dr.clip(seg.p, 1e-12, 1.0)
    term = dr.select(seg.valid, log_pass + dr.log(p) + log_density(seg, z), -dr.inf)
    high = dr.maximum(log_mix, term)
    safe = dr.select(dr.isinf(high), 0.0, high)
    log_mix = dr.select(dr.isinf(high), high, safe + dr.log(dr.exp(log_mix - safe) + dr.exp(term - safe)))
    log_pass = log_pass + dr.select(seg.valid, dr.log(dr.maximum(1.0 - seg.p, 1e-12)), 0.0)
    return log_mix, log_pass


def moment_step(moments: SubRayMoments, seg: Segment) -> SubRayMoments:
    """Add the next element along each (sub-)ray to its return probability and range moments."""
    weight = dr.select(seg.valid, dr.exp(moments.log_miss) * seg.p, 0.0)
    return SubRayMoments(
        log_miss=moments.log_miss + dr.select(seg.valid, dr.log(dr.maximum(1.0 - seg.p, 1e-12)), 0.0),
        p_return=moments.p_return + weight,
        m1=moments.m1 + weight * seg.mean,
        m2=moments.m2 + weight * (dr.square(seg.sigma) + dr.square(seg.mean)),
    )


@dataclass
class SensorModel:
    """Sensor defaults plus the effects applied on top of the scene's elements.

    Attributes:
        range_sigma: range noise (m) of elements that do not set their own.
        min_range: returns closer than this (m) are not reported (blind zone).
        max_range: elements farther than this (m) are not seen.
        max_segments: elements a ray may pass before it is declared a miss.
        effects: effects in application order.
    """

    range_sigma: float = 0.01
    min_range: float = 0.0
    max_range: float = 120.0
    max_segments: int = 16
    effects: list[Effect] = field(default_factory=list)

    def __post_init__(self):
        checks = [
            ("range_sigma", self.range_sigma >= 0, ">= 0 m"),
            ("min_range", self.min_range >= 0, ">= 0 m"),
            ("max_range", self.max_range > self.min_range, f"> min_range ({self.min_range} m)"),
            ("max_segments", 1 <= self.max_segments <= 256, "in [1, 256]"),
        ]
        for name, ok, allowed in checks:
            if not ok:
                raise ParameterError(f"sensor model: {name}={getattr(self, name)} must be {allowed}")

    # ------------------------------------------------------------------ rays
    def prepare_rays(self, rays: RayBatch) -> RayBatch:
        """Apply the effects' ray perturbations."""
        for effect in self.effects:
            rays = effect.perturb_rays(rays)
        return rays

    def apply_effects(self, seg: Segment, rays: RayBatch) -> Segment:
        """Apply every effect's segment edit, in order."""
        for effect in self.effects:
            seg = effect.modify_segment(seg, rays)
        return seg

    def virtual_segments(self, rays: RayBatch) -> list[Segment]:
        """Elements met before the scene's, from the effects' :meth:`Effect.virtual_segments`."""
        return [seg for effect in self.effects for seg in effect.virtual_segments(rays)]

    def likelihood_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        """Apply the effects' likelihood-only edits (:meth:`Effect.likelihood_segment`)."""
        for effect in self.effects:
            seg = effect.likelihood_segment(seg, rays)
        return seg

    def fan_out(self, rays: RayBatch) -> tuple[Effect, RayBatch, mi.Float] | None:
        """The effect that fans beams out into sub-rays (:meth:`Effect.footprint`), its sub-rays and weights.

        Returns None when no effect does (one ray per beam, the common case).
        """
        fans = [(e, e.footprint(rays)) for e in self.effects]
        fans = [(e, *fan) for e, fan in fans if fan is not None]
        if len(fans) > 1:
            raise ParameterError(f"sensor model: effects {[e.name for e, *_ in fans]} all fan beams out; keep one")
        return fans[0] if fans else None

    def _intersect(self, scene, table: ElementTable, rays: RayBatch, start: mi.Point3f):
        """One round: the next element along each ray, as a Segment (before effects)."""
        ray = mi.Ray3f(start, rays.direction)
        si = scene.ray_intersect(ray, mi.RayFlags.Minimal, True)
        nominal = dr.dot(si.p - rays.origin, rays.direction)
        valid = si.is_valid() & (nominal <= self.max_range)
        element = dr.select(valid, table.element_of(si), 0)
        seg = table.segment(si, valid, element, rays.origin, rays.direction, self.range_sigma)
        return seg, si.p

    # ------------------------------------------------------------- sampling
    def simulate_rays(self, scene, table: ElementTable, rays: RayBatch, seed: int = 0) -> dict:
        """Simulate the first return of every ray.

        Args:
            scene: a loaded Mitsuba scene.
            table: its :class:`ElementTable`.
            rays: the wavefront (world frame); lanes are compacted as rays terminate.
            seed: random seed.

        Returns:
            Dict of per-ray arrays named as :data:`CHANNELS`: ``range`` (m, NaN for a miss),
            ``hit`` (Bool), ``element_id``/``shape_id`` (``NO_ELEMENT`` for a miss), ``label``,
            ``cos_incidence``, ``nominal_range`` (m, NaN for a miss) and ``segments`` (elements
            traversed, including the one that returned). With a beam-divergence effect each beam's
            sub-rays are simulated and the effect combines their returns (:meth:`Effect.combine`).
        """
        rays = self.prepare_rays(rays)
        fan = self.fan_out(rays)
        if fan is None:
            return self._first_returns(scene, table, rays, seed)
        effect, sub, weight = fan
        return effect.combine(self._first_returns(scene, table, sub, seed), weight, rays.width)

    def _first_returns(self, scene, table: ElementTable, rays: RayBatch, seed: int) -> dict:
        """The sampling loop of :meth:`simulate_rays` on prepared rays (one lane per ray)."""
        n = rays.width
        out = {
            "range": dr.full(mi.Float, dr.nan, n),
            "hit": dr.full(mi.Bool, False, n),
            "element_id": dr.full(mi.UInt32, NO_ELEMENT, n),
            "shape_id": dr.full(mi.UInt32, NO_ELEMENT, n),
            "label": dr.zeros(mi.UInt32, n),
            "cos_incidence": dr.zeros(mi.Float, n),
            "nominal_range": dr.full(mi.Float, dr.nan, n),
            "segments": dr.zeros(mi.UInt32, n),
        }
        index = dr.arange(mi.UInt32, n)  # ray index (into `out`) of each live lane
        # ---------------- Virtual elements (outliers, clutter) before the scene ----------
        for v in range(len(self.virtual_segments(rays))):
            seg = self.virtual_segments(rays)[v]  # rebuilt on the compacted lanes
            returned = seg.valid & (uniform(seed, rays.ray_id, VIRTUAL_SEGMENT + v, 0) < seg.p)
            z = sample_range(seg, uniform(seed, rays.ray_id, VIRTUAL_SEGMENT + v, 1))
            for effect in self.effects:
                z = effect.finalize_range(z, rays)
            reported = returned & (z >= self.min_range)
            dr.scatter(out["range"], z, index, reported)
            dr.scatter(out["hit"], mi.Bool(True), index, reported)
            dr.eval(out)
            live = dr.compress(~returned)
            index = dr.gather(mi.UInt32, index, live)
            rays = rays.take(live)
        start = mi.Point3f(rays.origin)
        for k in range(self.max_segments):
            # ---------------- Trace the next element of every live ray ----------------
            seg, point = self._intersect(scene, table, rays, start)
            seg = self.apply_effects(seg, rays)

            # ---------------- Bernoulli draw: return or pass through ------------------
            returned = seg.valid & (uniform(seed, rays.ray_id, k, 0) < seg.p)
            z = sample_range(seg, uniform(seed, rays.ray_id, k, 1))
            for effect in self.effects:
                z = effect.finalize_range(z, rays)
            reported = returned & (z >= self.min_range)
            dr.scatter(out["range"], z, index, reported)
            dr.scatter(out["hit"], mi.Bool(True), index, reported)
            for name, value in (
                ("element_id", seg.element),
                ("shape_id", seg.shape),
                ("label", seg.label),
                ("cos_incidence", seg.cos_incidence),
                ("nominal_range", seg.nominal),
            ):
                dr.scatter(out[name], value, index, returned)
            dr.scatter(out["segments"], dr.opaque(mi.UInt32, k + 1), index, seg.valid)

            # ---------------- Keep the rays that passed through ------------------------
            passed = seg.valid & ~returned
            dr.eval(out, passed, point)
            live = dr.compress(passed)
            if dr.width(live) == 0:
                break
            index = dr.gather(mi.UInt32, index, live)
            rays = rays.take(live)
            start = dr.gather(mi.Point3f, point, live) + RESTART_OFFSET * rays.direction
        return out

    # ------------------------------------------------------------ likelihood
    def trace_segments(self, scene, table: ElementTable, rays: RayBatch) -> list:
        """Trace up to ``max_segments`` elements along every ray without gradients.

        Returns:
            One record per round: a dict with ``valid`` (the ray met an element within range),
            ``element`` (global element index) and ``si`` (the surface interaction), enough to
            rebuild the segments with gradients in :meth:`log_likelihood`. With a
            beam-divergence effect the records are those of the sub-rays.
        """
        records = []
        with dr.suspend_grad():
            rays = self.prepare_rays(rays)
            fan = self.fan_out(rays)
            rays = rays if fan is None else fan[1]
            start = mi.Point3f(rays.origin)
            dr.eval(rays.origin, rays.direction)  # perturbed once, not again in every round's kernel
            for _ in range(self.max_segments):
                ray = mi.Ray3f(start, rays.direction)
                si = scene.ray_intersect(ray, mi.RayFlags.Minimal, True)
                nominal = dr.dot(si.p - rays.origin, rays.direction)
                valid = si.is_valid() & (nominal <= self.max_range)
                element = dr.select(valid, table.element_of(si), 0)
                record = {"valid": valid, "element": element, "si": si}
                start = dr.select(valid, si.p + RESTART_OFFSET * rays.direction, start)
                dr.eval(valid, element, si.p, si.n, start)  # each round's kernel has the same code
                records.append(record)
                if not dr.any(valid):
                    break
        return records

    def log_likelihood(
        self,
        scene_table: ElementTable,
        rays: RayBatch,
        records: list,
        measured: mi.Float,
        hit: mi.Bool,
        resolution: float = 0.0,
    ) -> mi.Float:
        """Per-ray log-likelihood of measured ranges under the pass-through mixture.

        Args:
            scene_table: element table (its arrays may carry gradients).
            rays: the same rays given to :meth:`trace_segments`.
            records: its output.
            measured: measured ranges (m); ignored where ``hit`` is False.
            hit: True where the sensor reported a return.
            resolution: if > 0, score returns as probabilities of ``resolution``-wide range
                bins (density x resolution), as in the thesis's discretized evaluation.

        Returns:
            ``log sum_k P_k f_k(z)`` for returns and ``log prod_k (1 - p_k)`` for misses (nats).
            With a beam-divergence effect, the effect's :meth:`Effect.combine_log_likelihood` of
            the sub-rays' return moments (an approximation that effect documents).
        """
        rays = self.prepare_rays(rays)
        fan = self.fan_out(rays)
        if fan is not None:
            effect, sub, weight = fan
            ll = effect.combine_log_likelihood(
                self.sub_ray_moments(scene_table, sub, records), weight, dr.select(hit, measured, 0.0), hit, rays.width
            )
            return dr.select(hit, ll + math.log(resolution), ll) if resolution > 0 else ll
        log_pass = dr.zeros(mi.Float, dr.width(measured))
        log_mix = dr.full(mi.Float, -dr.inf, dr.width(measured))
        z = dr.select(hit, measured, 0.0)
        segments = [(seg, None) for seg in self.virtual_segments(rays)] + [(None, record) for record in records]
        for seg, record in segments:
            if record is not None:
                seg = scene_table.segment(
                    record["si"], record["valid"], record["element"], rays.origin, rays.direction, self.range_sigma
                )
                seg = self.apply_effects(seg, rays)
            log_mix, log_pass = mixture_step(log_mix, log_pass, self.likelihood_segment(seg, rays), z)
        if resolution > 0:
            log_mix = log_mix + dr.log(resolution)
        return dr.select(hit, log_mix, log_pass)

    def sub_ray_moments(self, scene_table: ElementTable, sub: RayBatch, records: list) -> SubRayMoments:
        """Return probability and range moments of each sub-ray's first return (virtual elements first)."""
        n = sub.width
        moments = SubRayMoments(
            log_miss=dr.zeros(mi.Float, n),
            p_return=dr.zeros(mi.Float, n),
            m1=dr.zeros(mi.Float, n),
            m2=dr.zeros(mi.Float, n),
        )
        for seg in self.virtual_segments(sub):
            moments = moment_step(moments, self.likelihood_segment(seg, sub))
        for record in records:
            seg = scene_table.segment(
                record["si"], record["valid"], record["element"], sub.origin, sub.direction, self.range_sigma
            )
            moments = moment_step(moments, self.likelihood_segment(self.apply_effects(seg, sub), sub))
        return moments
