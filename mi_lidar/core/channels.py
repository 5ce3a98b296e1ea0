"""Per-ray output channels: conversion between the core's arrays, range-image tensors and numpy.

Channel order (:data:`mi_lidar.core.sensor_model.CHANNELS`): ``range`` (m, NaN = miss), ``hit``,
``element_id``, ``shape_id`` (-1 = miss), ``label``, ``cos_incidence``, ``nominal_range`` (m),
``segments``. In tensors and EXR files every channel is float32; in :class:`~mi_lidar.core.log.Log`
attributes ids and labels are int32.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.sensor_model import CHANNELS, NO_ELEMENT

INTEGER_CHANNELS = ("element_id", "shape_id", "label", "segments")


def _as_float(name: str, value) -> mi.Float:
    if name == "hit":
        return dr.select(value, 1.0, 0.0)
    if name in ("element_id", "shape_id"):
        return dr.select(value == NO_ELEMENT, -1.0, mi.Float(value))
    return mi.Float(value)


def channels_to_tensor(out: dict, height: int, width: int) -> mi.TensorXf:
    """Stack the core's per-ray arrays into a (height, width, len(CHANNELS)) float32 tensor."""
    columns = mi.ArrayXf([_as_float(name, out[name]) for name in CHANNELS])
    return mi.TensorXf(dr.ravel(columns), shape=(height, width, len(CHANNELS)))  # channels interleaved per ray


def tensor_to_numpy(image) -> dict[str, np.ndarray]:
    """Split a (H, W, C) range-image tensor (``mi.render`` output) into named numpy channels."""
    array = np.asarray(image)
    if array.ndim != 3 or array.shape[2] != len(CHANNELS):
        raise ValueError(f"expected a (H, W, {len(CHANNELS)}) lidar image; got shape {array.shape}")
    result = {name: array[..., c] for c, name in enumerate(CHANNELS)}
    result["hit"] = result["hit"] > 0.5
    for name in INTEGER_CHANNELS:
        result[name] = result[name].astype(np.int32)
    return result


def channels_to_numpy(out: dict) -> dict[str, np.ndarray]:
    """The core's per-ray Dr.Jit arrays as numpy (ids -1 for misses, integer channels int32)."""
    result = {}
    for name in CHANNELS:
        value = np.asarray(out[name])
        if name in INTEGER_CHANNELS:  # uint32 -> int32 wraps NO_ELEMENT (2^32 - 1) to -1 in one copy
            value = value.astype(np.int32)
        result[name] = value
    return result
