"""Range noise laws added to every return (thesis eq. for the physics baseline)."""

from __future__ import annotations

import drjit as dr

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import MAX_SIGMA_M, ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import MAX_COS, Segment

MIN_COS = 0.01  # the footprint law's floor of |cos(incidence)|: tan(delta) <= 100


@register_effect
class RangeNoise(Effect):
    """Extra Gaussian range noise, added in quadrature to each element's own sigma.

    ``law`` selects sigma(r, delta) for nominal range r (m) and incidence angle delta:

    * ``constant``:     sigma = sigma0
    * ``proportional``: sigma = sigma0 + k r
    * ``physics``:      sigma^2 = sigma0^2 + K r^2 / cos(delta)  (the thesis's physics baseline)
    * ``footprint``:    sigma = sigma0 + k r tan(delta)

    The ``footprint`` law is the depth a patch of angular size ``k`` (rad) spans along the beam when
    seen at range ``r`` and incidence ``delta``: the spread of a beam footprint (mixed pixels) and of
    a mesh interpolated between returns ``k`` apart, both largest at grazing incidence and at depth
    edges, whose faces are seen edge-on (``tan(delta)`` is capped at ``1 / MIN_COS``). Within 4.9e-4 rad of
    normal incidence ``tan(delta)`` is held at 4.9e-4 (``cos`` at most :data:`~mi_lidar.core.segment.MAX_COS`),
    with no gradient: float32 holds three values of ``cos`` there, and the slope in ``cos`` is infinite at 1.
    """

    name = "range_noise"
    options = {"law": ("constant", "proportional", "physics", "footprint")}
    variant_options = ("law",)
    specs = {
        "sigma0": ParamSpec(
            0.0,
            "m",
            "constant part of the noise",
            lower=0.0,
            upper=MAX_SIGMA_M,
            fit_lower=1e-4,
            fit_start=0.002,
            fit_scale=0.01,
        ),
        # k differs by orders of magnitude between laws: 0.01 (1 cm per m) for the proportional law,
        # 1e-4 for the physics law's K (sigma 1 cm at 1 m, normal incidence).
        "k": ParamSpec(
            0.0,
            "m/m (proportional), 1 (physics K) or rad (footprint)",
            "range-dependent coefficient",
            lower=0.0,
            fit_start=1e-4,
            fit_scale=lambda effect: 1e-4 if effect.choices["law"] == "physics" else 0.01,
            only={"law": ("proportional", "physics", "footprint")},
        ),
    }

    def extra_variance(self, seg: Segment):
        """Variance (m^2) this law adds to each segment."""
        r = dr.maximum(seg.nominal, 0.0)
        law = self.choices["law"]
        if law == "constant":
            return dr.square(self["sigma0"]) + 0.0 * r
        if law == "proportional":
            return dr.square(self["sigma0"] + self["k"] * r)
        if law == "footprint":
            cos = dr.clip(seg.cos_incidence, MIN_COS, MAX_COS)  # below 1: tan's slope in cos is infinite there
            return dr.square(self["sigma0"] + self["k"] * r * dr.sqrt(1.0 - cos * cos) / cos)
        cos = dr.maximum(seg.cos_incidence, 1e-3)
        return dr.square(self["sigma0"]) + self["k"] * r * r / cos

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        return seg.with_(sigma=dr.sqrt(dr.square(seg.sigma) + self.extra_variance(seg)))
