"""The physics baseline: Gaussian range noise with sigma^2 = sigma0^2 + K r^2 / cos(incidence) (thesis ch. 3)."""

from __future__ import annotations

import drjit as dr

from mi_lidar.core.densities.base import UniformEscapeDensity, escape_segment, register_density
from mi_lidar.core.params import MAX_SIGMA_M, ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import SURFACE, Segment


@register_density
class PhysicsDensity(UniformEscapeDensity):
    """Gaussian returns whose variance grows with range and incidence, and a constant no-return rate.

    ``sigma^2 = sigma0^2 + K r^2 / cos(delta)`` with ``r`` the nominal range (m) and ``delta`` the
    incidence angle (unknown incidence counts as normal); an intercepted beam gives no return with
    probability ``p_null``; a beam that met nothing returns with probability ``escape_return``,
    uniformly on ``[0, z_max]`` (0 by default: it is a miss). ``sigma0``, ``k`` and ``p_null`` are
    differentiable and fitted by the one Adam fitter. Ellipsoid elements keep their own Gaussian.

    Example (XML): ``<string name="density" value="physics(sigma0=0.01, k=1e-5, p_null=0.02)"/>``.
    """

    name = "physics"
    specs = {
        "sigma0": ParamSpec(
            0.01, "m", "constant part of the noise", lower=0.0, upper=MAX_SIGMA_M, fit_lower=1e-4, fit_scale=0.01
        ),
        "k": ParamSpec(1e-5, "1", "range-incidence coefficient K", lower=0.0, fit_scale=1e-4),
        "p_null": ParamSpec(
            0.01, "1", "probability that an intercepted beam gives no return", lower=0.0, upper=0.999, fit_scale=0.01
        ),
        "escape_return": ParamSpec(
            0.0, "1", "probability that a beam that met nothing returns", lower=0.0, upper=1.0, fit=False
        ),
        "z_max": ParamSpec(80.0, "m", "largest range the sensor reports", lower=1e-3, upper=1e4, fit=False),
    }

    def prepare(self, seg: Segment, rays: RayBatch) -> Segment:
        surface = seg.kind == SURFACE
        cos = dr.maximum(dr.select(dr.isnan(seg.cos_incidence), 1.0, seg.cos_incidence), 1e-3)
        r = dr.maximum(seg.nominal, 0.0)
        sigma = dr.sqrt(dr.square(self["sigma0"]) + self["k"] * r * r / cos)
        return seg.with_(
            sigma=dr.select(surface, sigma, seg.sigma),
            drop=dr.select(surface, 1.0 - (1.0 - seg.drop) * (1.0 - self["p_null"]), seg.drop),
        )

    def escape(self, rays: RayBatch) -> Segment:
        return escape_segment(rays, drop=1.0 - self["escape_return"], sigma=1.0)
