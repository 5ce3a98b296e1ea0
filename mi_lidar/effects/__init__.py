"""Catalog of physical effects; see :mod:`mi_lidar.effects.base` for the interface."""

from .base import EFFECTS, Effect, FootprintEffect, ParamSpec, RayBatch, make_effect, parse_effects, register_effect
from .range_noise import RangeNoise
from .beam_offsets import BeamOffsets
from .range_bias import RangeBias
from .range_scale import RangeScale
from .extrinsics import Extrinsics

__all__ = [
    "EFFECTS", "Effect", "FootprintEffect", "ParamSpec", "RayBatch", "RangeNoise",
    "make_effect", "parse_effects", "register_effect",
]
from .incidence_dropout import IncidenceDropout
from .range_dropout import RangeDropout
from .label_dropout import LabelDropout
from .quantization import Quantization
from .outliers import Outliers
from .motion_distortion import MotionDistortion
from .random_dropout import RandomDropout
from .mixed_pixels import MixedPixels
from .multiple_returns import MultipleReturns
