"""Dropout that grows with the incidence angle: grazing beams return too little light."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import DropoutEffect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import MAX_COS, Segment


@register_effect
class IncidenceDropout(DropoutEffect):
    """Beams lost at grazing incidence: keep probability a function of the incidence angle.

    ``delta`` is the angle between the beam and the surface normal (``seg.cos_incidence``). Two laws:

    * ``law=cos`` (default): keep ``cos(delta)^gamma``. A Lambertian target returns power
      proportional to ``cos(delta)``; a detector whose threshold sits in the tail of the returned
      power drops beams faster, which ``gamma > 1`` models. ``gamma = 0`` disables it.
    * ``law=logistic``: drop ``1 / (1 + exp(-(delta - angle50) / width))`` with ``delta``, ``angle50``
      and ``width`` in degrees: a sensor that loses beams beyond a sharp angle (half of them at
      ``angle50``, from 12 % to 88 % over ``4 width``).

    Dropped beams stop (``mode=stop``, default) or pass on (``mode=pass``), see
    :class:`~mi_lidar.core.effects.base.DropoutEffect`. Differentiable in every parameter.

    Examples: ``incidence_dropout(gamma=2)``: a beam at 60 deg keeps 25 %;
    ``incidence_dropout(law=logistic, angle50=70, width=3)``.
    """

    name = "incidence_dropout"
    options = {"law": ("cos", "logistic"), "mode": ("stop", "pass")}
    variant_options = ("law",)
    specs = {
        "gamma": ParamSpec(
            0.0,
            "1",
            "exponent of cos(incidence) in the keep probability",
            lower=0.0,
            upper=50.0,
            fit_start=0.3,
            fit_scale=1.0,
            only={"law": ("cos",)},
        ),
        "angle50": ParamSpec(
            75.0,
            "deg",
            "incidence angle at which half the beams are lost",
            lower=0.0,
            upper=90.0,
            fit_start=75.0,
            fit_scale=5.0,
            only={"law": ("logistic",)},
        ),
        "width": ParamSpec(
            5.0,
            "deg",
            "width of the logistic transition",
            lower=0.1,
            upper=45.0,
            fit_start=5.0,
            fit_scale=1.0,
            only={"law": ("logistic",)},
        ),
    }

    def keep(self, seg: Segment, rays: RayBatch) -> mi.Float:
        cos = dr.clip(seg.cos_incidence, 1e-4, 1.0)
        if self.choices["law"] == "cos":
            return dr.exp(self["gamma"] * dr.log(cos))
        # below 1: acos has an infinite slope at normal incidence (NaN gradients for ray-moving effects)
        delta = dr.acos(dr.minimum(cos, MAX_COS)) * (180.0 / math.pi)
        return 1.0 - 1.0 / (1.0 + dr.exp(-(delta - self["angle50"]) / self["width"]))
