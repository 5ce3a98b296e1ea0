"""Dropout per class label: dark, shiny or transparent materials return fewer beams."""

from __future__ import annotations

import mitsuba as mi

from mi_lidar.core.effects.base import DropoutEffect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@register_effect
class LabelDropout(DropoutEffect):
    """Lose a fraction ``drop[l]`` of the beams intercepted by elements with label ``l``.

    ``drop`` holds one dropout probability per class label (the last value repeats for higher
    labels). Labels stand for reflectivity classes as well as semantic classes: give dark or
    specular materials their own label in the scene. Differentiable in ``drop``, fitted as a logit
    (labels that lose 2 % and 95 % of their beams fit alike). Dropped beams stop
    (``mode=stop``, default) or pass on (``mode=pass``).

    Example: ``label_dropout(drop=[0 0.3 0])``: elements of label 1 lose 30 % of their hits.
    """

    name = "label_dropout"
    specs = {
        "drop": ParamSpec(
            0.0,
            "1",
            "dropout probability of each label",
            lower=0.0,
            upper=1.0,
            per_label=True,
            fit_start=0.02,
            fit_scale=1.0,
            fit_transform="logit",
        )
    }

    def keep(self, seg: Segment, rays: RayBatch) -> mi.Float:
        return 1.0 - self.per_label("drop", seg.label)
