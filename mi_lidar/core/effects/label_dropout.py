"""Dropout per class label: dark, shiny or transparent materials return fewer beams."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, ParamSpec, register_effect
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class LabelDropout(Effect):
    """Scale the hit probability of elements with label ``l`` by ``1 - drop[l]``.

    ``drop`` holds one dropout probability per class label (the last value repeats for higher
    labels). Labels stand for reflectivity classes as well as semantic classes: give dark or
    specular materials their own label in the scene. Differentiable in ``drop``.

    Example: ``label_dropout(drop=[0 0.3 0])``: elements of label 1 lose 30 % of their hits.
    """

    name = "label_dropout"
    specs = {"drop": ParamSpec(0.0, "1", "dropout probability of each label", lower=0.0, upper=1.0)}
    fit_scales = {"drop": 0.2}
    fit_start = {"drop": 0.02}
    per_label = ("drop",)

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        values = self["drop"]
        drop = dr.gather(mi.Float, values, dr.minimum(seg.label, dr.width(values) - 1))
        return seg.with_(p=seg.p * (1.0 - drop))
