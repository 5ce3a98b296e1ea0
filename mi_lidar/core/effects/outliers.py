"""Outlier returns: clutter near the sensor (people, dust) and random readings anywhere."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import SURFACE, Segment

NO_ELEMENT = 0xFFFFFFFF


@register_effect
class Outliers(Effect):
    """Two virtual elements met before the scene: near clutter and uniform random returns.

    They are the short-reading and random components of the classic beam model (thesis ch. 2),
    written as permeable elements so that they take part in the pass-through mixture:

    * near clutter returns the beam with probability ``p_near`` at a range drawn from a
      half-normal of scale ``near_scale`` (m) (people and objects close to the sensor that the
      map does not hold);
    * random returns happen with probability ``p_uniform`` at a range uniform on
      ``[0, uniform_max]`` (m).

    A beam that passes both meets the scene as usual. ``p_near``, ``near_scale`` and
    ``p_uniform`` are differentiable; ``uniform_max`` is fixed (set it to the sensor's maximum
    range).

    Example: ``outliers(p_near=0.02, near_scale=2, p_uniform=0.01, uniform_max=80)``.
    """

    name = "outliers"
    specs = {
        "p_near": ParamSpec(
            0.0, "1", "probability of a near-clutter return", lower=0.0, upper=1.0, fit_start=0.01, fit_scale=0.02
        ),
        "near_scale": ParamSpec(
            2.0, "m", "scale of the half-normal near-clutter range", lower=1e-3, upper=1e3, fit_scale=0.5
        ),
        "p_uniform": ParamSpec(
            0.0, "1", "probability of a uniform random return", lower=0.0, upper=1.0, fit_start=0.005, fit_scale=0.01
        ),
        "uniform_max": ParamSpec(80.0, "m", "upper end of the uniform random range", lower=1e-3, upper=1e4, fit=False),
    }

    def virtual_segments(self, rays: RayBatch) -> list[Segment]:
        """The near-clutter and random-return elements, one lane per ray."""
        n = rays.width
        zero = dr.zeros(mi.Float, n)
        common = dict(
            valid=dr.full(mi.Bool, True, n),
            nominal=zero,
            lo=zero,
            cos_incidence=zero + 1.0,
            element=dr.full(mi.UInt32, NO_ELEMENT, n),
            shape=dr.full(mi.UInt32, NO_ELEMENT, n),
            label=dr.zeros(mi.UInt32, n),
            kind=dr.full(mi.UInt32, SURFACE, n),
        )
        near = Segment(p=zero + self["p_near"], mean=zero, sigma=zero + self["near_scale"], hi=zero + dr.inf, **common)
        top = self["uniform_max"]
        # A Gaussian 100x wider than the interval is flat on it to 5e-5 relative.
        uniform = Segment(
            p=zero + self["p_uniform"], mean=zero + 0.5 * top, sigma=zero + 100.0 * top, hi=zero + top, **common
        )
        return [near, uniform]
