"""Range scale: a multiplicative error of the time-of-flight clock."""

from __future__ import annotations

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class RangeScale(Effect):
    """Range scale ``z = scale * r`` (dimensionless) on every return.

    The whole return distribution of each element is scaled: mean, sigma and, for ellipsoids,
    the truncation chord. The nominal (geometric) range is unchanged. Differentiable.

    Example: ``range_scale(scale=1.002)``.
    """

    name = "range_scale"
    specs = {
        "scale": ParamSpec(1.0, "1", "factor applied to every returned range", lower=0.5, upper=2.0, fit_scale=0.002)
    }

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        s = self["scale"]
        return seg.with_(mean=seg.mean * s, sigma=seg.sigma * s, lo=seg.lo * s, hi=seg.hi * s)
