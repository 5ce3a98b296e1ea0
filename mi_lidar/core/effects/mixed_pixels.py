"""Mixed pixels: a diverging beam covers several surfaces and reports their energy-weighted range."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import FootprintEffect, SubRayMoments, register_effect
from mi_lidar.core.effects.beam_offsets import offset_direction
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch

# Sub-ray pattern of the footprint: (elevation, azimuth) offsets in units of ``divergence``.
PATTERN = ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
MIN_VARIANCE = 1e-8  # m^2: floor of the combined range variance


@register_effect
class MixedPixels(FootprintEffect):
    """Beam divergence: each beam is 5 sub-rays whose returns merge into one energy-weighted range.

    The footprint is the beam axis plus four sub-rays turned by ``divergence`` (rad) up, down,
    left and right in the sensor frame; each outer sub-ray carries ``edge_weight`` of the beam's
    energy and the axis the rest. Each sub-ray is simulated as an ordinary ray (pass-through,
    dropout, noise and the other effects); the beam returns when any sub-ray does, at the
    energy-weighted mean ``sum_j w_j z_j / sum_j w_j`` of the returning sub-rays. At an edge this
    puts points between the foreground and the background: the mixed pixels of real Lidars.
    Channels other than the range (element, label, incidence...) are those of the returning
    sub-ray with the largest weight.

    Likelihood (approximation). Each sub-ray's first return is summarised by its return
    probability ``r_j`` and the mean ``mu_j`` and variance ``v_j`` of its range (moments of the
    pass-through mixture with untruncated element Gaussians, :class:`SubRayMoments`). The beam
    misses with probability ``prod_j (1 - r_j)``; a return is Gaussian with mean
    ``sum_j a_j mu_j / A`` and variance ``sum_j a_j^2 v_j / A^2``, ``a_j = w_j r_j``,
    ``A = sum_j a_j``. This is exact when every sub-ray meets one opaque surface with Gaussian
    noise; with dropout or permeable elements it replaces the random set of returning sub-rays by
    its expectation and each sub-ray's multi-modal range by a Gaussian.

    ``divergence`` is fitted through the traced tangent planes of the sub-rays (which surface a
    sub-ray meets has no gradient); ``edge_weight`` is fixed.

    Example: ``mixed_pixels(divergence=0.003)`` (3 mrad, about a VLP-16's beam divergence).
    """

    name = "mixed_pixels"
    specs = {
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

    def combine(self, sub: dict, weight: mi.Float, n: int) -> dict:
        total, weighted, energy = dr.zeros(mi.Float, n), dr.zeros(mi.Float, n), dr.zeros(mi.Float, n)
        taken = dr.full(mi.Bool, False, n)
        out: dict = {}
        for j in range(len(PATTERN)):  # the axis first: it carries the largest weight
            index = dr.arange(mi.UInt32, n) + j * n
            hit = dr.gather(mi.Bool, sub["hit"], index)
            w = dr.gather(mi.Float, weight, index)
            total += dr.select(hit, w, 0.0)
            weighted += dr.select(hit, w * dr.gather(mi.Float, sub["range"], index), 0.0)
            energy += dr.select(hit, w * dr.gather(mi.Float, sub["intensity"], index), 0.0)
            for name, value in sub.items():
                mine = dr.gather(type(value), value, index)
                out[name] = mine if j == 0 else dr.select(~taken & hit, mine, out[name])
            taken |= hit
        out["hit"] = total > 0
        out["range"] = dr.select(out["hit"], weighted / dr.maximum(total, 1e-12), dr.nan)
        out["intensity"] = dr.round(energy)  # the returned power of every sub-ray that returned
        return out

    def combine_log_likelihood(
        self, moments: SubRayMoments, weight: mi.Float, z: mi.Float, hit: mi.Bool, n: int
    ) -> mi.Float:
        log_miss, a_sum, mean_sum, var_sum = (
            dr.zeros(mi.Float, n),
            dr.zeros(mi.Float, n),
            dr.zeros(mi.Float, n),
            dr.zeros(mi.Float, n),
        )
        for j in range(len(PATTERN)):
            index = dr.arange(mi.UInt32, n) + j * n
            r = dr.gather(mi.Float, moments.p_return, index)
            safe = dr.maximum(r, 1e-12)
            mu = dr.gather(mi.Float, moments.m1, index) / safe
            var = dr.maximum(dr.gather(mi.Float, moments.m2, index) / safe - dr.square(mu), 0.0)
            a = dr.gather(mi.Float, weight, index) * r
            log_miss += dr.gather(mi.Float, moments.log_miss, index)
            a_sum += a
            mean_sum += a * mu
            var_sum += dr.square(a) * var
        safe = dr.maximum(a_sum, 1e-12)
        mean = mean_sum / safe
        variance = dr.maximum(var_sum / dr.square(safe), MIN_VARIANCE)
        p_hit = dr.maximum(1.0 - dr.exp(log_miss), 1e-12)
        ll_hit = dr.log(p_hit) - 0.5 * dr.square(z - mean) / variance - 0.5 * dr.log(variance) - LOG_SQRT_2PI
        return dr.select(hit, ll_hit, log_miss)
