"""Multi-channel OpenEXR images (range images and per-ray channels), via the ``OpenEXR`` 3.x API.

Channels are looked up by name, never by position: EXR stores them in alphabetical order.
Float arrays are stored as 32-bit ``FLOAT`` (float16 loses centimetres); integer and boolean
arrays whose values fit in ``[0, 2**32)`` are stored as ``UINT`` and read back as ``uint32``;
other integer arrays (negative values) are stored as ``FLOAT`` when float32 represents every
value exactly, and rejected otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenEXR

from ..errors import LogFormatError
from ._atomic import atomic_path

_UINT_MAX = np.iinfo(np.uint32).max
_FLOAT32_EXACT = 2**24


def _storage_array(name: str, array: np.ndarray) -> np.ndarray:
    """Return ``array`` as the float32 or uint32 array OpenEXR will store for channel ``name``."""
    if array.ndim != 2:
        raise ValueError(f"EXR channel {name!r} has shape {array.shape}; expected (H, W)")
    if array.dtype == bool:
        return array.astype(np.uint32)
    if np.issubdtype(array.dtype, np.integer):
        if array.size == 0 or (array.min() >= 0 and array.max() <= _UINT_MAX):
            return array.astype(np.uint32)
        if np.abs(array).max() > _FLOAT32_EXACT:
            raise ValueError(
                f"EXR channel {name!r}: signed integers up to {np.abs(array).max()} cannot be stored "
                f"exactly (UINT needs values >= 0, FLOAT is exact only up to 2**24); "
                "offset the values to be non-negative"
            )
        return array.astype(np.float32)
    if np.issubdtype(array.dtype, np.floating):
        return array.astype(np.float32)
    raise ValueError(f"EXR channel {name!r} has dtype {array.dtype}; expected a float, integer or bool array")


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray]) -> Path:
    """Write named (H, W) channels to a ZIP-compressed scanline EXR, atomically.

    Args:
        path: Destination ``.exr`` file (written to a temporary file, then renamed).
        channels: Channel name -> (H, W) array; every channel must have the same shape.
            Floats become ``FLOAT`` (float32), non-negative integers and bools ``UINT``.

    Returns:
        The destination path.

    Raises:
        ValueError: No channel, mismatched shapes, or values no EXR pixel type holds exactly.
    """
    if not channels:
        raise ValueError("write_exr needs at least one channel")
    stored = {name: _storage_array(name, np.asarray(a)) for name, a in channels.items()}
    shapes = {a.shape for a in stored.values()}
    if len(shapes) != 1:
        raise ValueError(f"EXR channels have different shapes {sorted(shapes)}; all must be (H, W)")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in stored.items()}) as exr:
            exr.write(str(tmp))
    return Path(path)


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file.

    Args:
        path: An ``.exr`` file.

    Returns:
        Channel name -> (H, W) array (float32 for FLOAT, uint32 for UINT, float16 for HALF).

    Raises:
        LogFormatError: The file is missing, truncated or not an EXR image.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such EXR file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            return {name: np.array(channel.pixels) for name, channel in exr.channels().items()}
    except Exception as exc:  # OpenEXR raises plain RuntimeError/Exception subclasses.
        raise LogFormatError(f"{path}: not a readable EXR image ({exc})") from exc
