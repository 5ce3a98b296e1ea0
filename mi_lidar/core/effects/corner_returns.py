"""Corner returns: between the samples a mesh was built from, the beam sees one sample's surface."""

from __future__ import annotations

import drjit as dr

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class CornerReturns(Effect):
    """A triangle returns from the surface of one of its corners with probability ``share``.

    A mesh built from measured returns (a range-image mesh, a fitted ground) interpolates linearly
    between them. Where the surface between two samples is not the plane through them, the sensor
    does not see the plane: at a depth edge it sees the foreground or the background, in clutter
    (vegetation, poles, people) the object of one sample or the gap of another. This effect makes
    each triangle return, with probability ``share``, from the range at which the beam passes one of
    its vertices (vertex ``i`` with probability equal to the hit point's barycentric weight ``w_i``,
    so the nearest sample is the likeliest), and from the plane otherwise; each with the element's
    range noise (a corner's return is a sample's surface: it keeps the element's noise plus
    ``sigma``, and effects applied after this one widen the plane's returns only, the interpolation
    that is uncertain). On smooth surfaces the corners lie on the plane and nothing changes; at depth edges
    the samples land on the two sides of the edge, as the sensor's do, instead of in the air between
    them. See :mod:`mi_lidar.core.segment` for the density. ``share`` is differentiable, and so are
    the corners in the vertex positions. Elements other than triangles are unchanged.

    Example: ``corner_returns(share=0.8, sigma=0.01)``.
    """

    name = "corner_returns"
    specs = {
        "share": ParamSpec(
            0.0, "1", "probability that a return comes from a corner's surface", lower=0.0, upper=1.0, fit_start=0.5
        ),
        "sigma": ParamSpec(
            0.0,
            "m",
            "range noise added to a corner's return",
            lower=0.0,
            fit_lower=1e-4,
            fit_start=0.01,
            fit_scale=0.01,
        ),
    }

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        # one value each, broadcast where used (adding a literal zero array would resize the parameter)
        corner_sigma = dr.sqrt(dr.square(seg.sigma) + dr.square(self["sigma"]))
        return seg.with_(corner_share=self["share"], corner_sigma=corner_sigma)
