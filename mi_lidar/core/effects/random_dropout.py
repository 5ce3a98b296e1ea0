"""Dropout independent of range and angle: the max-range readings of the classic beam model."""

from __future__ import annotations

import mitsuba as mi

from mi_lidar.core.effects.base import DropoutEffect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class RandomDropout(DropoutEffect):
    """Lose a fraction ``p_drop`` of the intercepted beams, whatever the range or incidence.

    The classic beam model's max-range component (thesis ch. 2): with probability ``p_drop`` a
    beam that meets a surface reports no return (specular or dark targets, glass, electronics),
    whatever the range or incidence. ``p_drop = 0`` disables the effect. Differentiable. Dropped
    beams stop (``mode=stop``, default) or pass on (``mode=pass``).

    Example: ``random_dropout(p_drop=0.02)``: 2 % of the beams that meet an opaque wall are misses.
    """

    name = "random_dropout"
    specs = {
        "p_drop": ParamSpec(
            0.0,
            "1",
            "probability that a surface does not return the beam",
            lower=0.0,
            upper=1.0,
            fit_start=0.01,
            fit_scale=0.05,  # a step of 0.01 took 60 steps to reach 7 % of a 10 % dropout
        )
    }

    def keep(self, seg: Segment, rays: RayBatch) -> mi.Float:
        return 1.0 - self["p_drop"] + 0.0 * seg.nominal
