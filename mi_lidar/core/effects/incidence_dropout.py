"""Dropout that grows with the incidence angle: grazing beams return too little light."""

from __future__ import annotations

import drjit as dr

from mi_lidar.core.effects.base import Effect, ParamSpec, register_effect
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class IncidenceDropout(Effect):
    """Scale each element's hit probability by ``cos(delta)^gamma``.

    ``delta`` is the angle between the beam and the surface normal (``seg.cos_incidence``). A
    Lambertian target returns power proportional to ``cos(delta)``; a detector whose threshold
    sits in the tail of the returned power drops beams faster, which ``gamma > 1`` models.
    ``gamma = 0`` disables the effect. Differentiable in ``gamma``.

    Example: ``incidence_dropout(gamma=2)``: a beam at 60 deg keeps 25 % of its hits.
    """

    name = "incidence_dropout"
    specs = {"gamma": ParamSpec(0.0, "1", "exponent of cos(incidence) in the keep probability", lower=0.0, upper=50.0)}
    fit_scales = {"gamma": 1.0}
    fit_start = {"gamma": 0.3}

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        cos = dr.clip(seg.cos_incidence, 1e-4, 1.0)
        return seg.with_(p=seg.p * dr.exp(self["gamma"] * dr.log(cos)))
