"""Range scale: a multiplicative error of the time-of-flight clock."""

from __future__ import annotations

import drjit as dr

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import SURFACE, Segment


@register_effect
class RangeScale(Effect):
    """Range scale ``z = scale * r + noise`` (dimensionless) on every return.

    The location of each element's return is scaled: its mean and, for ellipsoids, the truncation
    chord. Its spread is not: the noise is added after the clock, from the nominal range, as in
    ``z = scale * r + noise(r)``. So the scale and the noise laws commute (a diagnosis that finds the
    noise first and the scale second fits the same noise as one that finds them the other way round;
    scaling the spread too would shrink a fitted noise by the scale). The nominal (geometric) range is
    unchanged. Differentiable.

    A surface's return moves by ``(scale - 1) r`` from its nominal range ``r``, whatever shifted it before: with a
    per-beam bias ``b`` it returns ``scale * r + b`` whether the bias comes before or after the scale in the model
    (scaling the shifted location gave ``scale * (r + b)`` after a bias, so the bias fitted beside a scale found
    after it was off by ``(scale - 1) b``: 2 % of it at scale 1.02). An ellipsoid's location and chord, which are not
    its nominal (entry) range, are scaled as they stand.

    Example: ``range_scale(scale=1.002)``.
    """

    name = "range_scale"
    specs = {
        "scale": ParamSpec(1.0, "1", "factor applied to every returned range", lower=0.5, upper=2.0, fit_scale=0.002)
    }

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        s = self["scale"]
        mean = dr.select(seg.kind == SURFACE, seg.mean + (s - 1.0) * seg.nominal, seg.mean * s)
        return seg.with_(mean=mean, lo=seg.lo * s, hi=seg.hi * s)
