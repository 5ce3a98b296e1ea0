"""Range quantization: the sensor reports ranges on a grid of fixed step."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment

MIN_VARIANCE = 1e-12  # m^2: floor of the widened variance (a micrometre)


@register_effect
class Quantization(Effect):
    """Round reported ranges to multiples of ``step`` (m).

    * Sampler: ``z -> step * round(z / step)`` after the range is drawn.
    * Likelihood (approximation): the rounding error is uniform on ``[-step/2, step/2]`` with
      variance ``step^2 / 12``; the likelihood adds that variance to each element's Gaussian
      instead of integrating the density over the rounding cell. The approximation is close when
      ``step`` is at most about twice the range sigma; for coarser steps the true likelihood is a
      staircase the Gaussian only matches in its first two moments.

    ``step`` is differentiable in the likelihood only (the rounding has no useful gradient).

    Example: ``quantization(step=0.02)`` (a 2 cm range resolution).
    """

    name = "quantization"
    specs = {
        "step": ParamSpec(
            0.01, "m", "range resolution of the sensor", lower=0.0, upper=1.0, fit_start=0.005, fit_scale=0.01
        )
    }

    def finalize_range(self, z: mi.Float, rays: RayBatch) -> mi.Float:
        step = self["step"]
        return dr.select(step > 0, dr.round(z / dr.maximum(step, 1e-9)) * step, z)

    def likelihood_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        """Add the rounding variance ``step^2 / 12`` (m^2) to the element's Gaussian."""
        # floored: a density whose own spread is 0 (NP-Reg) would give 0/0 at step 0
        variance = dr.maximum(dr.square(seg.sigma) + dr.square(self["step"]) / 12.0, MIN_VARIANCE)
        return seg.with_(sigma=dr.sqrt(variance))
