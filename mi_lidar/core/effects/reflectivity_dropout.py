"""Weak returns below the detection threshold: dark surfaces vanish at long range and grazing angles."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import DropoutEffect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class ReflectivityDropout(DropoutEffect):
    """Beams lost when the returned power falls below the detector's threshold.

    A Lambertian element of reflectivity ``rho`` (``seg.reflectivity``) at range ``r`` and incidence
    ``delta`` returns the power ``rho cos(delta) / r^2`` (the Lidar equation, in units of a white
    target's head-on return at 1 m). The detector keeps a beam with the logistic probability

    ``keep = 1 / (1 + exp(-(ln(rho cos(delta)) - 2 ln(r / range50)) / width))``

    so a white target seen head-on is kept half of the time at ``range50`` (m), and an element of
    reflectivity ``rho`` at ``range50 sqrt(rho cos(delta))``: a black tyre (``rho`` 0.04) is lost at a
    fifth of a white wall's range. ``width`` (nats of returned power) spreads the threshold (noise in
    the detector and in the reflectivity). Dropped beams stop (``mode=stop``, default) or pass on
    (``mode=pass``), see :class:`~mi_lidar.core.effects.base.DropoutEffect`. Differentiable in both
    parameters and in the elements' reflectivities.

    Example: ``reflectivity_dropout(range50=60, width=0.5)``: a wall of reflectivity 0.1 is kept half of
    the time at 19 m, 88 % at 11.5 m and 12 % at 31 m.
    """

    name = "reflectivity_dropout"
    specs = {
        "range50": ParamSpec(
            1000.0,
            "m",
            "range at which a white target seen head-on is lost half of the time",
            lower=0.1,
            upper=1e4,
            fit_start=80.0,
            fit_scale=5.0,
        ),
        "width": ParamSpec(
            0.5,
            "1",
            "spread of the detection threshold, in nats of returned power",
            lower=0.01,
            upper=10.0,
            fit_start=0.5,
            fit_scale=0.1,
            fit_lower=0.02,
        ),
    }

    def keep(self, seg: Segment, rays: RayBatch) -> mi.Float:
        power = dr.maximum(seg.reflectivity * dr.clip(seg.cos_incidence, 1e-6, 1.0), 1e-12)
        ratio = dr.maximum(seg.nominal, 1e-3) / self["range50"]
        margin = (dr.log(power) - 2.0 * dr.log(ratio)) / self["width"]
        return 1.0 / (1.0 + dr.exp(-margin))
