"""Multiple returns: a diverging beam yields several echoes and the sensor reports one of them."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import SubRayMoments, register_effect
from mi_lidar.core.effects.mixed_pixels import FOOTPRINT_SPECS, LOG_SQRT_2PI, MIN_VARIANCE, PATTERN, MixedPixels
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.segment import normal_cdf


@register_effect
class MultipleReturns(MixedPixels):
    """Beam divergence with echo selection: the sensor reports the first, strongest or last echo.

    The footprint is that of :class:`~mi_lidar.core.effects.mixed_pixels.MixedPixels` (the beam axis
    plus four sub-rays turned by ``divergence``, outer weight ``edge_weight``). Each returning
    sub-ray is an echo at its own range; ``mode`` picks the reported one:

    * ``first``: the nearest echo (a dual-return sensor's first return);
    * ``last``: the farthest echo (the ground under vegetation);
    * ``strongest``: the echo with the most energy, where echoes closer than ``separation`` (m)
      add their weights (the sensor cannot resolve them); ties go to the nearer echo.

    Channels other than the range are those of the reported sub-ray.

    Likelihood. Each sub-ray's first return is taken as a Gaussian ``N(mu_j, v_j)`` that happens
    with probability ``r_j`` (moments of its pass-through mixture, :class:`SubRayMoments`), the
    sub-rays independent. ``first`` then has the density
    ``sum_j r_j phi_j(z) prod_{i != j} (1 - r_i Phi_i(z))`` and ``last`` the same with
    ``1 - r_i (1 - Phi_i(z))``; both are exact when each sub-ray meets one opaque surface.
    ``strongest`` takes the density of ``first``: echoes closer than ``separation`` merge, and the
    sampler reports the nearest echo of the winning group, so on one surface (all echoes merged)
    the two coincide exactly; at an edge, or behind a permeable crown, where the farther group
    carries more energy the approximation gives the nearer surface the return (measured on the
    bundled street: total-variation distance 0.19 between sampled and scored ranges).

    Example: ``multiple_returns(mode=last, divergence=0.003)``.
    """

    name = "multiple_returns"
    options = {"mode": ("first", "strongest", "last")}
    variant_options = ("mode",)
    specs = {
        **FOOTPRINT_SPECS,
        "separation": ParamSpec(
            0.3, "m", "echoes closer than this merge (strongest mode)", lower=0.0, upper=10.0, fit=False
        ),
    }

    def combine(self, sub: dict, weight: mi.Float, n: int, u: mi.Point2f) -> dict:
        m, mode = len(PATTERN), self.choices["mode"]
        lanes = [dr.arange(mi.UInt32, n) + j * n for j in range(m)]
        hits = [dr.gather(mi.Bool, sub["hit"], i) for i in lanes]
        ranges = [dr.gather(mi.Float, sub["range"], i) for i in lanes]
        weights = [dr.gather(mi.Float, weight, i) for i in lanes]
        if mode == "strongest":
            scores = []
            for j in range(m):
                energy = sum(
                    dr.select(hits[i] & (dr.abs(ranges[i] - ranges[j]) <= self["separation"]), weights[i], 0.0)
                    for i in range(m)
                )
                scores.append(energy - 1e-6 * ranges[j])  # ties: the nearer echo
        else:
            scores = [-r if mode == "first" else r for r in ranges]
        best, chosen = dr.full(mi.Float, -dr.inf, n), dr.zeros(mi.UInt32, n)
        for j in range(m):
            better = hits[j] & (scores[j] > best)
            best = dr.select(better, scores[j], best)
            chosen = dr.select(better, lanes[j], chosen)
        out = {name: dr.gather(type(value), value, chosen) for name, value in sub.items()}
        out["hit"] = dr.isfinite(best)
        out["range"] = dr.select(out["hit"], out["range"], dr.nan)
        return out

    def combine_log_likelihood(
        self, moments: SubRayMoments, weight: mi.Float, z: mi.Float, hit: mi.Bool, n: int
    ) -> mi.Float:
        m, mode = len(PATTERN), self.choices["mode"]
        r, log_phi, cdf, log_miss = [], [], [], dr.zeros(mi.Float, n)
        for j in range(m):
            index = dr.arange(mi.UInt32, n) + j * n
            rj = dr.gather(mi.Float, moments.p_return, index)
            safe = dr.maximum(rj, 1e-12)
            mu = dr.gather(mi.Float, moments.m1, index) / safe
            var = dr.maximum(dr.gather(mi.Float, moments.m2, index) / safe - dr.square(mu), MIN_VARIANCE)
            r.append(rj)
            log_phi.append(-0.5 * dr.square(z - mu) / var - 0.5 * dr.log(var) - LOG_SQRT_2PI)
            cdf.append(normal_cdf((z - mu) / dr.sqrt(var)))
            log_miss += dr.gather(mi.Float, moments.log_miss, index)
        density = dr.zeros(mi.Float, n)
        for j in range(m):
            term = r[j] * dr.exp(log_phi[j])
            for i in range(m):
                if i != j:
                    beyond = 1.0 - cdf[i] if mode == "last" else cdf[i]
                    term *= 1.0 - r[i] * beyond
            density += term
        return dr.select(hit, dr.log(dr.maximum(density, 1e-30)), log_miss)
