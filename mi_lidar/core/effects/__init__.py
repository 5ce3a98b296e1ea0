"""Catalog of physical effects; see :mod:`mi_lidar.core.effects.base` for the interface.

Importing this package registers every catalog effect (each module ends with ``@register_effect``).
"""

from mi_lidar.core.effects.base import EFFECTS, Effect, FootprintEffect, make_effect, parse_effects, register_effect
from mi_lidar.core.effects.beam_offsets import BeamOffsets
from mi_lidar.core.effects.corner_returns import CornerReturns
from mi_lidar.core.effects.extrinsics import Extrinsics
from mi_lidar.core.effects.incidence_dropout import IncidenceDropout
from mi_lidar.core.effects.label_dropout import LabelDropout
from mi_lidar.core.effects.mixed_pixels import MixedPixels
from mi_lidar.core.effects.motion_distortion import MotionDistortion
from mi_lidar.core.effects.multiple_returns import MultipleReturns
from mi_lidar.core.effects.outliers import Outliers
from mi_lidar.core.effects.quantization import Quantization
from mi_lidar.core.effects.random_dropout import RandomDropout
from mi_lidar.core.effects.range_bias import RangeBias
from mi_lidar.core.effects.range_dropout import RangeDropout
from mi_lidar.core.effects.range_noise import RangeNoise
from mi_lidar.core.effects.range_scale import RangeScale
from mi_lidar.core.effects.reflectivity_dropout import ReflectivityDropout
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch

__all__ = [
    "EFFECTS",
    "BeamOffsets",
    "CornerReturns",
    "Effect",
    "Extrinsics",
    "FootprintEffect",
    "IncidenceDropout",
    "LabelDropout",
    "MixedPixels",
    "MotionDistortion",
    "MultipleReturns",
    "Outliers",
    "ParamSpec",
    "Quantization",
    "RandomDropout",
    "RangeBias",
    "RangeDropout",
    "RangeNoise",
    "RangeScale",
    "RayBatch",
    "ReflectivityDropout",
    "make_effect",
    "parse_effects",
    "register_effect",
]
