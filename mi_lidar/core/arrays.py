"""Helpers for handing numpy arrays to Dr.Jit."""

from __future__ import annotations

import numpy as np


def aligned(array: np.ndarray, alignment: int = 64) -> np.ndarray:
    """A contiguous copy of ``array`` starting on an ``alignment``-byte boundary.

    Dr.Jit wraps numpy memory without copying and compiles aligned and unaligned loads into
    different kernels; aligned inputs let every batch reuse one compiled kernel.
    """
    array = np.ascontiguousarray(array)
    raw = np.empty(array.nbytes + alignment, np.uint8)
    start = -raw.ctypes.data % alignment
    out = raw[start : start + array.nbytes].view(array.dtype).reshape(array.shape)
    out[...] = array
    return out
