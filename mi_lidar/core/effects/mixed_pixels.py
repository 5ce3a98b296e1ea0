"""Mixed pixels: a diverging beam covers several surfaces and reports their energy-weighted range."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import OPEN_WINDOW, FootprintEffect, SubRayMoments, register_effect
from mi_lidar.core.effects.beam_offsets import offset_direction
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import is_open, normal_mass

# Sub-ray pattern of the footprint: (elevation, azimuth) offsets in units of ``divergence``.
PATTERN = ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
MIN_VARIANCE = 1e-8  # m^2: floor of the combined range variance


FOOTPRINT_SPECS = {
    "divergence": ParamSpec(
        0.0,
        "rad",
        "angle between the beam axis and its outer sub-rays",
        lower=0.0,
        upper=0.05,
        fit_start=0.001,
        fit_scale=0.001,
    ),
    "edge_weight": ParamSpec(
        0.15, "1", "energy share of each of the four outer sub-rays", lower=0.0, upper=0.25, fit=False
    ),
}


def _sub(values, j: int, n: int):
    """Lane block ``j`` (sub-ray ``j`` of every beam) of a sub-ray array."""
    return dr.gather(type(values), values, dr.arange(mi.UInt32, n) + j * n)


@register_effect
class MixedPixels(FootprintEffect):
    """Beam divergence: at a depth edge a beam reports the foreground, the background or a range in between.

    The footprint is the beam axis plus four sub-rays turned by ``divergence`` (rad) up, down,
    left and right in the sensor frame; each outer sub-ray carries ``edge_weight`` of the beam's
    energy and the axis the rest. Each sub-ray is simulated as an ordinary ray (pass-through,
    dropout, noise and the other effects); the beam returns when any sub-ray does. Of its returns,
    a share ``share`` is *in between*: the energy-weighted mean ``sum_j w_j r_j / sum_j w_j`` of the
    returning sub-rays' nominal ranges plus the range noise of one sub-ray; the others are *pure*:
    the return of one sub-ray, chosen with probability proportional to its energy. Where every
    sub-ray meets the same surface both are that surface's return; at an edge they are the mixed
    pixels of real Lidars (in-between points) and the foreground and background points around them.
    Channels other than the range (element, label, incidence...) are those of the chosen sub-ray.

    Likelihood (approximation). Each sub-ray's first return is summarised by its return
    probability ``r_j`` and the mean ``mu_j`` and variance ``v_j`` of its range (moments of the
    pass-through mixture with untruncated element Gaussians, :class:`SubRayMoments`). With
    ``a_j = w_j r_j`` and ``A = sum_j a_j``, the beam misses with probability ``prod_j (1 - r_j)``
    and a return has density
    ``share N(z; sum_j a_j mu_j / A, sum_j a_j v_j / A) + (1 - share) sum_j (a_j / A) N(z; mu_j, v_j)``.
    This replaces the random set of returning sub-rays by its expectation and each sub-ray's
    multi-modal range by a Gaussian.

    ``divergence`` is fitted through the traced tangent planes of the sub-rays (which surface a
    sub-ray meets has no gradient); ``share`` is fitted; ``edge_weight`` is fixed.

    Example: ``mixed_pixels(divergence=0.003, share=0.6)`` (3 mrad, about a VLP-16's beam
    divergence; 60 % of edge returns in between).
    """

    name = "mixed_pixels"
    specs = {
        **FOOTPRINT_SPECS,
        "share": ParamSpec(
            1.0, "1", "share of returns in between the sub-rays' ranges", lower=0.0, upper=1.0, fit_start=0.5
        ),
    }

    def footprint(self, rays: RayBatch) -> tuple[RayBatch, mi.Float]:
        n, m = rays.width, len(PATTERN)
        lane = dr.arange(mi.UInt32, m * n)
        beam, j = lane % n, lane // n
        sub = rays.take(beam)
        rotation, _ = sub.sensor_frame()
        local = mi.Vector3f(rotation.T @ sub.direction)
        d_elevation = dr.gather(mi.Float, mi.Float([p[0] for p in PATTERN]), j) * self["divergence"]
        d_azimuth = dr.gather(mi.Float, mi.Float([p[1] for p in PATTERN]), j) * self["divergence"]
        direction = mi.Vector3f(rotation @ offset_direction(local, d_elevation, d_azimuth))
        edge = self["edge_weight"]
        weight = dr.select(j == 0, 1.0 - (m - 1) * edge, edge)
        return RayBatch(
            origin=sub.origin,
            direction=direction,
            beam=sub.beam,
            time=sub.time,
            ray_id=sub.ray_id * m + j,
            sensor_rotation=sub.sensor_rotation,
            sensor_position=sub.sensor_position,
        ), weight

    def combine(self, sub: dict, weight: mi.Float, n: int, u: mi.Point2f) -> dict:
        m = len(PATTERN)
        hits = [_sub(sub["hit"], j, n) for j in range(m)]
        weights = [dr.select(hits[j], _sub(weight, j, n), 0.0) for j in range(m)]
        total = sum(weights[1:], weights[0])
        # one returning sub-ray, chosen by energy: the first whose cumulative share exceeds u.x
        target, running = u.x * total, dr.zeros(mi.Float, n)
        chosen, found = dr.zeros(mi.UInt32, n), dr.full(mi.Bool, False, n)
        for j in range(m):
            running += weights[j]
            pick = ~found & hits[j] & (running > target)
            chosen = dr.select(pick, dr.arange(mi.UInt32, n) + j * n, chosen)
            found |= pick
        out = {name: dr.gather(type(value), value, chosen) for name, value in sub.items()}
        out["hit"] = total > 0
        # the weighted mean's offset from the chosen sub-ray's range, summed as differences (float32 would round
        # a sum of ranges by 1.5e-5 m at 250 m)
        offsets = (
            w * dr.select(h, _sub(sub["nominal_range"], j, n) - out["nominal_range"], 0.0)
            for j, (w, h) in enumerate(zip(weights, hits))
        )
        shift = sum(offsets, dr.zeros(mi.Float, n)) / dr.maximum(total, 1e-12)
        in_between = u.y < self["share"]
        out["range"] = dr.select(out["hit"], out["range"] + dr.select(in_between, shift, 0.0), dr.nan)
        if "intensity" in sub:  # the returned power of every sub-ray that returned
            energy = sum((w * _sub(sub["intensity"], j, n) for j, w in enumerate(weights)), dr.zeros(mi.Float, n))
            out["intensity"] = dr.round(energy)
        return out

    def combine_log_likelihood(
        self, moments: SubRayMoments, weight: mi.Float, z: mi.Float, hit: mi.Bool, n: int, window: tuple = OPEN_WINDOW
    ) -> mi.Float:
        m = len(PATTERN)
        inside = dr.zeros(mi.Float, n)  # the pure sub-ray laws' mass in the window, weighted
        log_miss, a_sum, mean, var_sum, pure = (dr.zeros(mi.Float, n) for _ in range(5))
        for j in range(m):
            r = _sub(moments.p_return, j, n)
            mu = _sub(moments.mean, j, n)
            var = dr.maximum(_sub(moments.variance, j, n), MIN_VARIANCE)
            a = _sub(weight, j, n) * r
            log_miss += _sub(moments.log_miss, j, n)
            a_sum += a
            mean += a / dr.maximum(a_sum, 1e-30) * (mu - mean)  # running mean: no sum of ranges to round
            var_sum += a * var
            pure += a * dr.exp(-0.5 * dr.square(z - mu) / var) / dr.sqrt(var)
            if not is_open(*window):
                inside += a * normal_mass(mu, dr.sqrt(var), *window)
        safe = dr.maximum(a_sum, 1e-12)
        variance = dr.maximum(var_sum / safe, MIN_VARIANCE)
        between = dr.exp(-0.5 * dr.square(z - mean) / variance) / dr.sqrt(variance)
        share = self["share"]
        density = (share * between + (1.0 - share) * pure / safe) * math.exp(-LOG_SQRT_2PI)
        p_hit = dr.maximum(1.0 - dr.exp(log_miss), 1e-12)
        if not is_open(*window):
            reported = p_hit * (share * normal_mass(mean, dr.sqrt(variance), *window) + (1.0 - share) * inside / safe)
            log_miss = dr.log(dr.clip(1.0 - reported, 1e-12, 1.0))
        return dr.select(hit, dr.log(p_hit) + dr.log(dr.maximum(density, 1e-30)), log_miss)
