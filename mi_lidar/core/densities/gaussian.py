"""The element Gaussian: each element returns its own truncated Gaussian (mi-lidar's default density)."""

from __future__ import annotations

import mitsuba as mi

from mi_lidar.core.densities.base import ReturnDensity, register_density
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment, log_density, sample_range


@register_density
class ElementGaussian(ReturnDensity):
    """Each element returns ``N(mean, sigma^2)`` truncated to ``[lo, hi]`` (:mod:`mi_lidar.core.segment`).

    A surface returns its nominal range with its ``range_sigma`` (or the sensor's); an ellipsoid its
    3D Gaussian restricted to the ray, on the chord. No parameters of its own: the element table
    and the effects (noise laws, bias, scale, dropout) set everything.

    Example (XML): ``<string name="density" value="gaussian"/>`` (the default).
    """

    name = "gaussian"

    def log_prob(self, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
        return log_density(seg, z)

    def sample(self, seg: Segment, u: mi.Point2f, rays: RayBatch) -> mi.Float:
        return sample_range(seg, u.x)
