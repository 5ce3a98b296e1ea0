"""Per-beam range bias: a constant offset added to every return of a beam."""

from __future__ import annotations

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class RangeBias(Effect):
    """Per-beam range bias ``z = r + bias[beam]`` (m).

    The whole return distribution of each element moves: the Gaussian's mean and, for
    ellipsoids, its truncation chord. The nominal (geometric) range is unchanged. Differentiable.

    Example: ``range_bias(bias=[0.01 -0.004 0.002])`` (m; the last value repeats for the
    remaining beams).
    """

    name = "range_bias"
    specs = {
        "bias": ParamSpec(
            0.0, "m", "offset added to every return of the beam", lower=-5.0, upper=5.0, per_beam=True, fit_scale=0.01
        )
    }

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        bias = self.per_beam("bias", rays.beam)
        return seg.with_(mean=seg.mean + bias, lo=seg.lo + bias, hi=seg.hi + bias)
