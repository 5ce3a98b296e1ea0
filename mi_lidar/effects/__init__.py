"""Catalog of physical effects; see :mod:`mi_lidar.effects.base` for the interface."""

from .base import EFFECTS, Effect, ParamSpec, RayBatch, make_effect, parse_effects, register_effect
from .range_noise import RangeNoise

__all__ = [
    "EFFECTS", "Effect", "ParamSpec", "RayBatch", "RangeNoise",
    "make_effect", "parse_effects", "register_effect",
]
