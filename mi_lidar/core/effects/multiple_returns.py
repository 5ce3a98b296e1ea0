"""Multiple returns: a diverging beam yields several echoes and the sensor reports one of them."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import OPEN_WINDOW, SubRayMoments, register_effect
from mi_lidar.core.effects.mixed_pixels import FOOTPRINT_SPECS, LOG_SQRT_2PI, MIN_VARIANCE, PATTERN, MixedPixels
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.segment import is_open, normal_cdf, normal_mass

ORDER_SCALE = 1e-3  # m: softness of the order of two echoes in the likelihood


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

    Echoes are ordered and merged by their sub-rays' nominal ranges (where the surfaces are), and the
    reported echo carries the range noise of its sub-ray only: one surface seen by every sub-ray
    gives one echo with one noise draw, as a real sensor reports it. Channels other than the range
    are those of the reported sub-ray.

    Likelihood. Each sub-ray's first return is summarised by its return probability ``r_j`` and the
    mean ``mu_j`` and variance ``v_j`` of its range (moments of its pass-through mixture,
    :class:`SubRayMoments`), the sub-rays independent. The reported echo is sub-ray ``j`` with
    probability ``pi_j`` proportional to ``r_j prod_{i != j} (1 - r_i c_ij)``, with ``c_ij`` the
    probability that sub-ray ``i`` lies before ``j`` (``first``: ``Phi((mu_j - mu_i) / ORDER_SCALE)``, a
    millimetre softness that keeps the order differentiable; ``last``: after), normalised to the
    probability that any sub-ray returns; a return at ``z`` has the density
    ``(1 - prod_j (1 - r_j)) sum_j pi_j N(z; mu_j, v_j)``. It is exact where every sub-ray meets an
    opaque surface.
    ``strongest`` takes the density of ``first``: echoes closer than ``separation`` merge, and the
    sampler reports the nearest echo of the winning group, so on one surface (all echoes merged)
    the two coincide exactly; at an edge, or behind a permeable crown, where the farther group
    carries more energy the approximation gives the nearer surface the return.

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
        where = [dr.gather(mi.Float, sub["nominal_range"], i) for i in lanes]  # echoes sit at the surfaces
        weights = [dr.gather(mi.Float, weight, i) for i in lanes]
        if mode == "strongest":
            scores = []
            for j in range(m):
                energy = sum(
                    dr.select(hits[i] & (dr.abs(where[i] - where[j]) <= self["separation"]), weights[i], 0.0)
                    for i in range(m)
                )
                scores.append(energy - 1e-6 * where[j])  # ties: the nearer echo
        else:
            scores = [-r if mode == "first" else r for r in where]
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
        self, moments: SubRayMoments, weight: mi.Float, z: mi.Float, hit: mi.Bool, n: int, window: tuple = OPEN_WINDOW
    ) -> mi.Float:
        m, later = len(PATTERN), self.choices["mode"] == "last"
        r, mu, var, log_miss = [], [], [], dr.zeros(mi.Float, n)
        for j in range(m):
            index = dr.arange(mi.UInt32, n) + j * n
            r.append(dr.gather(mi.Float, moments.p_return, index))
            mu.append(dr.gather(mi.Float, moments.mean, index))
            var.append(dr.maximum(dr.gather(mi.Float, moments.variance, index), MIN_VARIANCE))
            log_miss += dr.gather(mi.Float, moments.log_miss, index)
        share, total = [], dr.zeros(mi.Float, n)
        for j in range(m):
            term = r[j]
            for i in range(m):
                if i != j:
                    ahead = (mu[i] - mu[j] if later else mu[j] - mu[i]) / ORDER_SCALE
                    term *= 1.0 - r[i] * normal_cdf(ahead)
            share.append(term)
            total += term
        density = dr.zeros(mi.Float, n)
        for j in range(m):
            log_phi = -0.5 * dr.square(z - mu[j]) / var[j] - 0.5 * dr.log(var[j]) - LOG_SQRT_2PI
            density += share[j] * dr.exp(log_phi)
        p_any = dr.maximum(1.0 - dr.exp(log_miss), 1e-12)
        density *= p_any / dr.maximum(total, 1e-30)
        if not is_open(*window):
            masses = (share[j] * normal_mass(mu[j], dr.sqrt(var[j]), *window) for j in range(m))
            inside = sum(masses, dr.zeros(mi.Float, n))
            log_miss = dr.log(dr.clip(1.0 - p_any * inside / dr.maximum(total, 1e-30), 1e-12, 1.0))
        return dr.select(hit, dr.log(dr.maximum(density, 1e-30)), log_miss)
