"""Corner returns: between the samples a mesh was built from, the beam sees one sample's surface."""

from __future__ import annotations

import drjit as dr

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import MAX_SIGMA_M, ParamSpec
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

    ``sigma`` is set, not fitted: a corner's return is the sensor seeing a measured sample's surface
    again, so its spread is the sensor's own noise (the sample's and the new return's: ``sigma`` of
    the order of the element's). Fitted, it becomes a catch-all for returns that lie off every
    surface: on the shared Ouster frame it grew to 8 cm and on the VLP-16 capture to 0.6 m, so
    that half the sampled returns of *flat* faces scattered that far off them. Those scans are
    rough where the sensor's are smooth (scan matchers read local surface geometry), and a
    sampled range lands far from the measured one on most rays.

    Example: ``corner_returns(share=0.8, sigma=0.01)``.
    """

    name = "corner_returns"
    specs = {
        "share": ParamSpec(
            0.0, "1", "probability that a return comes from a corner's surface", lower=0.0, upper=1.0, fit_start=0.5
        ),
        "sigma": ParamSpec(
            0.0, "m", "range noise added to a corner's return (fixed)", lower=0.0, upper=MAX_SIGMA_M, fit=False
        ),
    }

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        # one value each, broadcast where used (adding a literal zero array would resize the parameter)
        corner_sigma = dr.sqrt(dr.square(seg.sigma) + dr.square(self["sigma"]))
        return seg.with_(corner_share=self["share"], corner_sigma=corner_sigma)
