"""The sensor model and the one sampling loop: first return through permeable elements.

Both the ``lidar`` integrator (``mi.render`` of an XML scene) and :func:`mi_lidar.simulate` call
:meth:`SensorModel.simulate_rays`. Along each ray the elements ``k = 1..K`` are met in order (the
effects' virtual elements first); each intercepts the beam with probability ``p_k``, loses an
intercepted beam with probability ``drop_k`` and otherwise returns it at a range drawn from the
model's return density; a beam that is not intercepted passes on. A beam that meets nothing more
may still return through the density's escape law. The likelihood of the same model is
:func:`mi_lidar.core.likelihood.mixture_log_likelihood`, so sampling and scoring agree by
construction.

Randomness is counter-based (a TEA hash of seed, ray id, segment and stream,
:mod:`mi_lidar.core.streams`), so a ray's draws do not depend on which other rays are traced with
it: the same seed gives the same scan on both paths, and different seeds give independent scans. One
uniform number decides an element's outcome: ``u < p (1 - drop)`` returns, ``u < p`` loses the beam,
otherwise it passes. A return from a scene element reports an intensity drawn from the model's
:class:`~mi_lidar.core.intensity.IntensityModel` (stream 3 of the element's draw); stray returns
(virtual elements, the escape law) report 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from mi_lidar.core.densities import ElementGaussian, ReturnDensity
from mi_lidar.core.effects.base import Effect, FootprintEffect
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.intensity import IntensityModel
from mi_lidar.core.params import DISTANCE_LIMIT, MAX_DISTANCE_M, MAX_SIGMA_M, SIGMA_LIMIT, check_limit
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment, sample_range
from mi_lidar.core.streams import MAX_UNIFORM, NeighbourStreams, check_seed, uniform, uniforms
from mi_lidar.core.trace import RESTART_OFFSET, mitsuba_ray, next_hit

NO_ELEMENT = 0xFFFFFFFF
VIRTUAL_SEGMENT = 1000  # random-stream segment index of the first virtual element
ESCAPE_SEGMENT = 2000  # random-stream segment index of the escape law
FOOTPRINT_SEGMENT = 3000  # random-stream segment index of a footprint effect's choices per beam
CHANNELS = (
    "range",
    "hit",
    "element_id",
    "shape_id",
    "label",
    "cos_incidence",
    "nominal_range",
    "segments",
    "intensity",
)
INTENSITY_STREAM = 3  # random stream of a return's intensity
TINY_WINDOW = 1e-12  # smallest share of a return law inside the range window (keeps its log finite)


@dataclass
class SensorModel:
    """Sensor defaults, the return density, and the effects applied on top of the scene's elements.

    Attributes:
        range_sigma: range noise (m) of elements that do not set their own, up to
            :data:`~mi_lidar.core.params.MAX_SIGMA_M` (1000 m).
        min_range: returns closer than this (m) are not reported (blind zone).
        max_range: elements farther than this (m) are not seen, and returns reported beyond it are not
            reported: ``[min_range, max_range]`` is the sensor's range window (:meth:`censor`). Up to
            :data:`~mi_lidar.core.params.MAX_DISTANCE_M` (1e8 m), or ``inf`` for no far end.
        max_segments: elements a ray may pass before it is declared a miss.
        effects: effects in application order.
        density: the return density of every element (default: each element's Gaussian).
        intensity: the returned intensity (sensor units) of every element.
    """

    range_sigma: float = 0.01
    min_range: float = 0.0
    max_range: float = 120.0
    max_segments: int = 16
    effects: list[Effect] = field(default_factory=list)
    density: ReturnDensity = field(default_factory=ElementGaussian)
    intensity: IntensityModel = field(default_factory=IntensityModel)

    def __post_init__(self):
        check_limit("sensor model", "range_sigma", self.range_sigma, MAX_SIGMA_M, SIGMA_LIMIT)
        check_limit("sensor model", "min_range", self.min_range, MAX_DISTANCE_M, DISTANCE_LIMIT)
        check_limit("sensor model", "max_range", self.max_range, MAX_DISTANCE_M, DISTANCE_LIMIT, open_end=True)
        checks = [
            ("max_range", self.max_range > self.min_range, f"> min_range ({self.min_range} m)"),
            ("max_segments", 1 <= self.max_segments <= 256, "in [1, 256]"),
        ]
        for name, ok, allowed in checks:
            if not ok:
                raise ParameterError(f"sensor model: {name}={getattr(self, name)} must be {allowed}")

    @property
    def parts(self) -> list:
        """The density, the intensity model and the effects: every object holding parameters of this model."""
        return [self.density, self.intensity, *self.effects]

    # ------------------------------------------------------------------ rays
    def prepare_rays(self, rays: RayBatch) -> RayBatch:
        """Apply the effects' ray perturbations."""
        for effect in self.effects:
            rays = effect.perturb_rays(rays)
        return rays

    def fan_out(self, rays: RayBatch) -> tuple[FootprintEffect, RayBatch, mi.Float] | None:
        """The effect that fans beams out into sub-rays (:meth:`Effect.footprint`), its sub-rays and weights.

        Returns None when no effect does (one ray per beam, the common case).
        """
        fans = [(e, fan) for e in self.effects if isinstance(e, FootprintEffect) and (fan := e.footprint(rays))]
        if len(fans) > 1:
            raise ParameterError(f"sensor model: effects {[e.name for e, _ in fans]} all fan beams out; keep one")
        return (fans[0][0], *fans[0][1]) if fans else None

    # ------------------------------------------------------------------ segments
    def apply_effects(self, seg: Segment, rays: RayBatch) -> Segment:
        """The law of a scene element as the sampler draws it: the density's, then every effect's edit."""
        seg = self.density.prepare(seg, rays)
        for effect in self.effects:
            seg = effect.modify_segment(seg, rays)
        return seg

    def segment_law(self, seg: Segment, rays: RayBatch, virtual: bool = False, escape: bool = False) -> Segment:
        """The law of an element as the likelihood scores it.

        Scene elements get :meth:`apply_effects`; the escape segment gets the density's law only;
        virtual elements (outliers) keep their own. All then get the effects' likelihood-only edits
        (the continuous stand-ins of post-processing such as quantization).
        """
        if escape:
            seg = self.density.prepare(seg, rays)
        elif not virtual:
            seg = self.apply_effects(seg, rays)
        for effect in self.effects:
            seg = effect.likelihood_segment(seg, rays)
        return seg

    def censor(self, seg: Segment, log_f: mi.Float, rays: RayBatch):
        """A segment's loss probability and return log density as seen through the range window.

        The sensor reports a return only within ``[min_range, max_range]`` (the sampler drops the
        others, :meth:`_reported`); a draw outside is lost like a dropped beam (no return, nothing behind
        revealed). With ``W`` the probability that a return of ``seg`` lies in the window
        (:meth:`ReturnDensity.window`), the element
        loses the beam with ``1 - (1 - drop) W`` and returns ``z`` with density ``f(z) / W`` given that it
        returns, so that ``(1 - drop) f(z)`` inside the window is unchanged. Beams fanned out by a footprint
        effect see the window once their sub-rays are combined
        (:meth:`~mi_lidar.core.effects.base.FootprintEffect.combine_log_likelihood`); virtual elements are drawn
        inside it (:meth:`virtual_segments`) and need no censoring.

        Args:
            seg: the segment after :meth:`segment_law`.
            log_f: (lanes,) log density (1/m) of the measured range under its law.

        Returns:
            ``(drop, log_f)`` to fold into the mixture.
        """
        inside = self.density.window(seg, self.min_range, self.max_range, rays)
        inside = dr.clip(dr.select(seg.valid, inside, 1.0), TINY_WINDOW, 1.0)
        return 1.0 - (1.0 - seg.drop) * inside, log_f - dr.log(inside)

    def virtual_segments(self, rays: RayBatch) -> list[Segment]:
        """Elements met before the scene's, from the effects' :meth:`Effect.virtual_segments`.

        Their laws are truncated to the range window: a virtual element stands for returns the sensor
        reports (clutter, random readings), so none of its draws falls outside and is lost. Left whole,
        a random-return law wider than the window would lose its far draws and stand in for a dropout.
        """
        return [
            seg.with_(lo=dr.maximum(seg.lo, self.min_range), hi=dr.minimum(seg.hi, self.max_range))
            for effect in self.effects
            for seg in effect.virtual_segments(rays)
        ]

    # ------------------------------------------------------------- sampling
    def simulate_rays(self, scene, table: ElementTable, rays: RayBatch, seed: int = 0, evaluate: bool = True) -> dict:
        """Simulate the first return of every ray.

        Args:
            scene: a loaded Mitsuba scene.
            table: its :class:`ElementTable`.
            rays: the wavefront (world frame); lanes are compacted as rays terminate.
            seed: random seed, 0 .. 2**32 - 1 (:func:`~mi_lidar.core.streams.check_seed`).
            evaluate: evaluate the outputs before returning them. False leaves the last step (the
                draw at the returning element) to the kernel that reads the outputs, so that a caller
                that rearranges them at once (the range-image tensor of ``mi.render``) writes them once;
                read such outputs in one ``dr.eval`` (each ``np.asarray`` of a channel would recompute it).

        Returns:
            Dict of per-ray arrays named as :data:`CHANNELS`: ``range`` (m, NaN for a miss),
            ``hit`` (Bool), ``element_id``/``shape_id`` (``NO_ELEMENT`` for a miss), ``label``,
            ``cos_incidence``, ``nominal_range`` (m, NaN for a miss), ``segments`` (elements
            traversed, including the one that returned) and ``intensity`` (sensor units, 0 for a
            miss or a stray return). With a beam-divergence effect each beam's
            sub-rays are simulated and the effect combines their returns (:meth:`Effect.combine`).
        """
        check_seed(seed)
        rays = self.prepare_rays(rays)
        fan = self.fan_out(rays)
        if fan is None:
            return self._first_returns(scene, table, rays, seed, evaluate)
        effect, sub, weight = fan
        choice = uniforms(seed, rays.ray_id, FOOTPRINT_SEGMENT)
        out = effect.combine(self._first_returns(scene, table, sub, seed, final=False), weight, rays.width, choice)
        z, reported = self._reported(out["range"], rays, out["hit"])  # the beam's return, not its sub-rays'
        out["range"], out["hit"] = dr.select(reported, z, dr.nan), reported
        if "intensity" in out:
            out["intensity"] = dr.select(reported, out["intensity"], 0.0)
        return out

    def _reported(self, z: mi.Float, rays: RayBatch, returned: mi.Bool, final: bool = True) -> tuple[mi.Float, mi.Bool]:
        """Post-processed ranges (m) and the lanes that report them (returned, within the range window).

        ``final=False`` (the sub-rays of a footprint, combined later): the raw draws and every return.
        """
        if not final:
            return z, returned
        for effect in self.effects:
            z = effect.finalize_range(z, rays)
        return z, returned & (z >= self.min_range) & (z <= self.max_range)

    def _report(
        self,
        out: dict,
        index: mi.UInt32,
        rays: RayBatch,
        returned: mi.Bool,
        z: mi.Float,
        intensity=0.0,
        final: bool = True,
    ) -> None:
        """Write the reported ranges (post-processed, blind zone applied) and intensities of the lanes that returned."""
        z, reported = self._reported(z, rays, returned, final)
        dr.scatter(out["range"], z, index, reported)
        dr.scatter(out["hit"], mi.Bool(True), index, reported)
        if "intensity" in out:  # sample_trace draws ranges only
            dr.scatter(out["intensity"], mi.Float(intensity), index, reported)

    def _virtual_returns(self, out: dict, rays: RayBatch, seed: int | NeighbourStreams, final: bool = True) -> mi.Bool:
        """Draw the effects' virtual elements (outliers, clutter) of every lane, in order.

        Returns:
            The lanes whose beam passed them all and goes on into the scene.
        """
        everyone = dr.arange(mi.UInt32, rays.width)
        alive = dr.full(mi.Bool, True, rays.width)
        for v, seg in enumerate(self.virtual_segments(rays)):
            u = uniform(seed, rays.ray_id, VIRTUAL_SEGMENT + v, 0)
            returned = alive & seg.valid & (u < seg.p * (1.0 - seg.drop))
            z = sample_range(seg, uniform(seed, rays.ray_id, VIRTUAL_SEGMENT + v, 1))
            self._report(out, everyone, rays, returned, z, final=final)
            alive = alive & ~(seg.valid & (u < seg.p))
        return alive

    def _first_returns(
        self, scene, table: ElementTable, rays: RayBatch, seed: int, evaluate: bool = True, final: bool = True
    ) -> dict:
        """The sampling loop of :meth:`simulate_rays` on prepared rays (one lane per ray).

        The rays walk through their elements in a symbolic Dr.Jit loop that only decides where each
        beam ends (returned, lost, met nothing more, or passed ``max_segments`` elements): it
        traces preliminary intersections and compiles only what the draw reads (``p`` and ``drop``;
        the surface interaction only when an effect reads the incidence). The range is then drawn
        once per ray, at the element that returned it, from that element's surface interaction.
        Every ray walks its first :data:`FIRST_PHASE` elements; the rays still passing through are
        then compacted and walk the rest in the same compiled loop, so that SIMD packets of
        mostly finished rays do not wait for a few long ones.
        """
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
            "intensity": dr.zeros(mi.Float, n),
        }
        alive = self._virtual_returns(out, rays, seed, final)  # virtual elements (outliers, clutter) come first
        first = min(FIRST_PHASE, self.max_segments)
        end, going, start = self._pass_through(
            scene, table, rays, alive, rays.origin, _BeamEnds.empty(n), 0, first, seed
        )
        dr.eval(end, going, start)
        index = dr.compress(going)  # the rays still passing through: compacted for the rest of the walk
        if dr.width(index) > 0:
            # keep only `end` of the rest of the walk, evaluated before the scatter: unevaluated outputs
            # would still read the phase-1 `end`, and scattering into it would copy it (+200 MB at 4M rays)
            rest = self._pass_through(
                scene,
                table,
                rays.take(index),
                True,
                dr.gather(mi.Point3f, start, index),
                dr.gather(_BeamEnds, end, index),
                first,
                self.max_segments,
                seed,
            )[0]
            dr.eval(rest)
            dr.scatter(end, rest, index)
            dr.eval(end)

        # ---------------- Draw the range at the element that returned the beam ----------------
        ray = mitsuba_ray(end.start, rays.direction, table.ray_length)
        si = end.hit.compute_surface_interaction(ray, mi.RayFlags.Minimal, end.returned)
        seg = table.traced_segment(si, end.returned, end.element, rays.origin, rays.direction, self.range_sigma)
        seg = self.apply_effects(seg, rays)
        z = self.density.sample(seg, uniforms(seed, rays.ray_id, end.segments - 1), rays)
        intensity = self.intensity.sample(seg, uniform(seed, rays.ray_id, end.segments - 1, INTENSITY_STREAM), rays)
        z, reported = self._reported(z, rays, end.returned, final)
        out["range"] = dr.select(reported, z, out["range"])
        out["intensity"] = dr.select(reported, intensity, out["intensity"])
        out["hit"] = out["hit"] | reported
        for name, value in (
            ("element_id", seg.element),
            ("shape_id", seg.shape),
            ("label", seg.label),
            ("cos_incidence", seg.cos_incidence),
            ("nominal_range", seg.nominal),
        ):
            out[name] = dr.select(end.returned, value, out[name])
        out["segments"] = end.segments
        self._escape(out, dr.arange(mi.UInt32, n), rays, end.escaped, seed, final)
        if evaluate:
            dr.eval(out)
        return out

    def _pass_through(
        self, scene, table, rays: RayBatch, going, start: mi.Point3f, end: _BeamEnds, first: int, last: int, seed: int
    ) -> tuple[_BeamEnds, mi.Bool, mi.Point3f]:
        """Walk ``rays`` from ``start`` through their elements ``first .. last - 1`` (one symbolic loop).

        Args:
            going: the beams that go in (a mask or True).
            start: where each ray continues from, m.
            end: what the beams met before element ``first``.

        Returns:
            ``(end, going, start)``: where each beam ended, the beams still passing through after
            element ``last - 1`` (with elements left to meet) and where they continue from.
        """
        n = rays.width
        origin, direction = rays.origin, rays.direction
        max_k = self.max_segments

        def passing(k, going, start, end):
            return going & (k < last_k)

        def meet_element(k, going, start, end):
            # ---------------- Trace the next element (its surface details wait for the return) --------
            pi, point, valid, element = next_hit(scene, table, start, origin, direction, self.max_range, going)
            si = pi.compute_surface_interaction(
                mitsuba_ray(start, direction, table.ray_length), mi.RayFlags.Minimal, valid
            )
            seg = table.traced_segment(si, valid, element, origin, direction, self.range_sigma)
            seg = self.apply_effects(seg, rays)  # only p and drop are used here: the rest is not compiled

            # ---------------- One draw: return, lose the beam, or pass through ---------
            u = uniform(seed, rays.ray_id, k, 0)
            returned = valid & (u < seg.p * (1.0 - seg.drop))
            k = k + 1
            end = _BeamEnds(  # a finished lane keeps its state: the element it ended at
                element=element,
                hit=pi,
                start=start,
                segments=dr.select(valid, k, end.segments),
                returned=returned,
                escaped=~valid,
            )
            going = valid & (u >= seg.p) & (k < max_k)
            return k, going, mi.Point3f(point + RESTART_OFFSET * direction), end

        last_k = dr.opaque(mi.UInt32, last)  # opaque: both phases run the same kernel
        state = (
            dr.opaque(mi.UInt32, first, n),  # k: elements met so far (random-stream segment)
            going & dr.full(mi.Bool, True, n),  # going: the beam goes on to the next element
            mi.Point3f(start),  # where each ray continues from, m
            end,  # where each beam ended
        )
        _, going, start, end = dr.while_loop(state, passing, meet_element, label="lidar pass-through")
        return end, going, start

    def sample_trace(
        self, table: ElementTable, rays: RayBatch, rounds, seed: int | NeighbourStreams = 0, active=None
    ) -> tuple[mi.Float, mi.Bool]:
        """One draw of every ray's reported range from an existing trace, with the sampler's rules.

        For segments another tracer found (:func:`~mi_lidar.core.trace.rounds_from_segments`, e.g. a
        planar log's ray march) or a Mitsuba trace (:func:`~mi_lidar.core.trace.trace_rounds`): element
        ``k`` of a ray draws from the same random streams as in :meth:`simulate_rays`, so both give
        the same range for the same seed. Footprint effects are not supported here.

        A :class:`~mi_lidar.core.streams.NeighbourStreams` in place of the seed draws the streams
        correlated between neighbouring beams. Then the outcomes along a ray are decided by one number
        per ray, carried from element to element: a beam that passes element ``k`` (``u >= p_k``) meets
        the next with what is left of it, ``(u - p_k) / (1 - p_k)``, uniform again given the pass. Each
        beam's law is the same; neighbouring beams that share their number stop at the same depth of
        the pass-through law, although their elements differ in number and order.

        ``active`` (``mi.Bool`` per ray; default: every ray) draws only those rays, the others report a
        miss: a ray's draw depends on its own ray id and elements only, the same as in a draw of every ray.

        Returns:
            ``(range, hit)`` per ray (m, NaN for a miss).
        """
        check_seed(seed)
        rays = self.prepare_rays(rays)
        n = rays.width
        out = {"range": dr.full(mi.Float, dr.nan, n), "hit": dr.full(mi.Bool, False, n)}
        alive = self._virtual_returns(out, rays, seed)
        if active is not None:
            alive &= active
        carried = uniform(seed, rays.ray_id, 0, 0) if isinstance(seed, NeighbourStreams) else None
        for k, r in enumerate(rounds.rounds):
            r = r.take(dr.compress(dr.gather(mi.Bool, alive, r.ray)))  # only the beams still going draw
            if r.width == 0:
                break  # the next round's beams are a subset of this round's
            sub = rays.take(r.ray)
            base = (
                table.segment(r, True, r.element, sub.origin, sub.direction, self.range_sigma)
                if r.cached is None
                else table.cached_segment(r, dr.full(mi.Bool, True, r.width), self.range_sigma)
            )
            seg = self.apply_effects(base, sub)
            u = uniform(seed, sub.ray_id, k, 0) if carried is None else dr.gather(mi.Float, carried, r.ray)
            returned = u < seg.p * (1.0 - seg.drop)
            self._report(out, r.ray, sub, returned, self.density.sample(seg, uniforms(seed, sub.ray_id, k), sub))
            dr.scatter(alive, False, r.ray, u < seg.p)
            if carried is not None:
                rest = dr.clip((u - seg.p) / dr.maximum(1.0 - seg.p, 1e-12), 0.0, MAX_UNIFORM)
                dr.scatter(carried, rest, r.ray, u >= seg.p)
            dr.eval(out, alive, carried)
        self._escape(out, dr.arange(mi.UInt32, n), rays, alive, seed)
        if active is not None:
            return dr.select(active, out["range"], dr.nan), out["hit"] & active
        return out["range"], out["hit"]

    def _escape(
        self,
        out: dict,
        index: mi.UInt32,
        rays: RayBatch,
        escaped: mi.Bool,
        seed: int | NeighbourStreams,
        final: bool = True,
    ) -> None:
        """Draw the escape law's return (if the density has one) for the lanes that met nothing more."""
        escape = self.density.escape(rays)
        if escape is None or not dr.any(escaped):
            return
        escape = self.density.prepare(escape, rays)
        u = uniform(seed, rays.ray_id, ESCAPE_SEGMENT, 0)
        returned = escaped & escape.valid & (u < escape.p * (1.0 - escape.drop))
        z = self.density.sample(escape, uniforms(seed, rays.ray_id, ESCAPE_SEGMENT), rays)
        self._report(out, index, rays, returned, z, final=final)
        dr.eval(out)


FIRST_PHASE = 2  # elements every ray may pass before the rays still passing through are compacted


@dataclass
class _BeamEnds:
    """Where each beam ended (one lane per ray): the state the pass-through loop carries.

    Attributes:
        element: the last element met: the one that returned the beam where ``returned``.
        hit: its preliminary intersection (the surface interaction is computed once, after the loop).
        start: where the ray that met it started, m.
        segments: elements met, including the one where the beam ended.
        returned: the beam returned from ``element``.
        escaped: the beam met nothing more within range.
    """

    element: mi.UInt32
    hit: mi.PreliminaryIntersection3f
    start: mi.Point3f
    segments: mi.UInt32
    returned: mi.Bool
    escaped: mi.Bool

    @classmethod
    def empty(cls, n: int) -> _BeamEnds:
        """``n`` beams that have met nothing yet."""
        return cls(
            element=dr.full(mi.UInt32, NO_ELEMENT, n),
            hit=dr.zeros(mi.PreliminaryIntersection3f, n),
            start=dr.zeros(mi.Point3f, n),
            segments=dr.zeros(mi.UInt32, n),
            returned=dr.full(mi.Bool, False, n),
            escaped=dr.full(mi.Bool, False, n),
        )
