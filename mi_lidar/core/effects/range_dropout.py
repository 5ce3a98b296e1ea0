"""Dropout that grows with range: far targets return too little light to be detected."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import DropoutEffect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment

REFERENCE_RANGE = 10.0  # m: range at which ``rate`` is the negative log keep probability


@register_effect
class RangeDropout(DropoutEffect):
    """Keep each intercepted beam with probability ``exp(-rate * (r / 10 m)^power)``.

    ``r`` is the element's nominal range (m). ``rate`` is the negative log keep probability at
    10 m (``rate = 0.1``: 90.5 % kept at 10 m); ``power`` sets how fast dropout grows with range
    (2 for a return power falling as ``1 / r^2`` against a noisy threshold). ``rate = 0``
    disables the effect. Both parameters are differentiable. Dropped beams stop (``mode=stop``,
    default) or pass on (``mode=pass``).

    Example: ``range_dropout(rate=0.2, power=2)``: keeps 82 % at 10 m and 45 % at 20 m.
    """

    name = "range_dropout"
    specs = {
        "rate": ParamSpec(
            0.0, "1", "negative log keep probability at 10 m", lower=0.0, upper=100.0, fit_start=0.05, fit_scale=0.1
        ),
        "power": ParamSpec(2.0, "1", "growth exponent of the dropout with range", lower=0.25, upper=8.0, fit_scale=0.5),
    }

    def keep(self, seg: Segment, rays: RayBatch) -> mi.Float:
        x = dr.maximum(seg.nominal, 1e-6) / REFERENCE_RANGE
        return dr.exp(-self["rate"] * dr.exp(self["power"] * dr.log(x)))
