"""Multi-channel OpenEXR images (range images and per-ray channels), via the ``OpenEXR`` 3.x API.

Channels are looked up by name, never by position: EXR stores them in alphabetical order.
Float arrays are stored as 32-bit ``FLOAT`` (float16 loses centimetres); integer and boolean
arrays whose values fit in ``[0, 2**32)`` are stored as ``UINT`` and read back as ``uint32``;
other integer arrays (negative values) are stored as ``FLOAT`` when float32 represents every
value exactly, and rejected otherwise.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.core.log import Log
from mi_lidar.core.strict_json import dumps, dumps_exact, loads_exact

_UINT_MAX = np.iinfo(np.uint32).max
_FLOAT32_EXACT = 2**24
ANGLE_TOLERANCE = 1e-6  # rad: float32 rounds pi and pi/2 up by less than 1e-7


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


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> Path:
    """Write named (H, W) channels to a ZIP-compressed scanline EXR, atomically.

    Args:
        path: Destination ``.exr`` file (written to a temporary file, then renamed).
        channels: Channel name -> (H, W) array; every channel must have the same shape.
            Floats become ``FLOAT`` (float32), non-negative integers and bools ``UINT``.
        metadata: Optional extra string attributes stored in the EXR header.

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
    header.update({key: str(value) for key, value in (metadata or {}).items()})
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in stored.items()}) as exr:
            try:
                exr.write(str(tmp))
            except RuntimeError as exc:  # OpenEXR's word for any failed write ('... File too large.')
                said = str(exc).replace(f' to image file "{tmp}"', "")
                raise OSError(errno.EIO, f"could not write the image (OpenEXR: {said})", os.fspath(path)) from exc
    return Path(path)


@contextlib.contextmanager
def _captured(said: list[str]):
    """Keep what OpenEXR prints about a damaged file off the terminal (a Python-level 'Warning: Exception raised
    reading pixel data' and the C library's '(EXR_ERR_BAD_CHUNK_LEADER) ...' on file descriptor 2): descriptors
    1 and 2 point to a temporary file for the read, whose lines are appended to ``said`` at the end, so the
    LogFormatError raised can say the library's reason once, on one line."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(fd) for fd in (1, 2)]
    with tempfile.TemporaryFile() as sink:
        python = io.StringIO()
        try:
            for fd in (1, 2):
                os.dup2(sink.fileno(), fd)
            with contextlib.redirect_stdout(python), contextlib.redirect_stderr(python):
                yield
        finally:
            for fd, copy in zip((1, 2), saved):
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            text = python.getvalue() + sink.read().decode("utf-8", "replace")
            said.extend(line.strip() for line in text.splitlines() if line.strip())


def read_exr(path: str | os.PathLike, with_metadata: bool = False):
    """Read every channel of an EXR file.

    Args:
        path: An ``.exr`` file.
        with_metadata: Also return the header's string attributes.

    Returns:
        Channel name -> (H, W) array (float32 for FLOAT, uint32 for UINT, float16 for HALF); with
        ``with_metadata``, the pair ``(channels, metadata)``.

    Raises:
        LogFormatError: The file is missing, truncated or not an EXR image.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such EXR file")
    said: list[str] = []
    try:
        with _captured(said), OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: np.array(channel.pixels) for name, channel in exr.channels().items()}
            metadata = {k: v for k, v in exr.header().items() if isinstance(v, str)}
    except Exception as exc:  # OpenEXR raises plain RuntimeError/Exception subclasses.
        if not os.access(path, os.R_OK):
            raise unreadable(path) from exc
        reason = next((line.replace(f"{path}: ", "") for line in said if line.startswith(f"{path}: ")), str(exc))
        raise LogFormatError(
            f"{path}: not a readable EXR image ({reason}); the file is damaged or cut short: re-create or copy it again"
        ) from exc
    return (channels, metadata) if with_metadata else channels


def write_exr_log(log: Log, path: str | os.PathLike, scan: int = 0) -> Path:
    """Write one scan as a float32 EXR range image.

    Channels: ``range`` (m, NaN = miss), ``hit`` (UINT), ``elevation`` and ``azimuth`` (rad, from
    the ray directions), ``time`` (s since the scan's first ray), ``origin.x/y/z`` (m) when any
    origin is non-zero, and every numeric attribute as ``attr.<name>``. The header holds the
    scan's start time, pose and sensor metadata as JSON strings.
    """
    one = log.scan(scan)
    direction = one.directions[0].astype(np.float64)
    times = one.times[0]
    channels = {
        "range": np.where(one.hit[0], one.ranges[0], np.nan).astype(np.float32),
        "hit": one.hit[0],
        "elevation": np.arcsin(np.clip(direction[..., 2], -1, 1)),
        "azimuth": np.arctan2(direction[..., 1], direction[..., 0]),
        "time": times - times.min(),
    }
    if np.any(one.origins != 0):
        channels.update({f"origin.{a}": one.origins[0, ..., i] for i, a in enumerate("xyz")})
    channels.update({f"attr.{k}": v[0] for k, v in one.attributes.items() if np.asarray(v).dtype.kind in "biuf"})
    metadata = {
        "mi_lidar_start_time": repr(float(times.min())),
        "mi_lidar_pose": dumps(one.poses[0]),
        "mi_lidar_sensor": dumps_exact(one.sensor, default=str),
    }
    return write_exr(path, channels, metadata)


def read_exr_log(path: str | os.PathLike) -> Log:
    """Read an EXR range image written by :func:`write_exr_log` as a one-scan log.

    Raises:
        LogFormatError: Unreadable file, missing ``range``/``elevation``/``azimuth`` channels, or an elevation
            beyond +-pi/2 or an azimuth beyond +-pi rad.
    """
    channels, metadata = read_exr(path, with_metadata=True)
    missing = [c for c in ("range", "elevation", "azimuth") if c not in channels]
    if missing:
        raise LogFormatError(f"{path}: EXR lacks channels {missing}; expected an mi-lidar range image")
    try:
        start = float(metadata.get("mi_lidar_start_time", "0"))
        pose = np.array(loads_exact(metadata.get("mi_lidar_pose", "null")) or np.eye(4).tolist(), dtype=np.float64)
        sensor = loads_exact(metadata.get("mi_lidar_sensor", "{}"))
    except (ValueError, TypeError) as exc:
        raise LogFormatError(f"{path}: malformed mi_lidar header attribute ({exc})") from exc
    if pose.shape != (4, 4) or not isinstance(sensor, dict):
        raise LogFormatError(f"{path}: mi_lidar_pose must be a 4x4 matrix and mi_lidar_sensor an object")
    ranges = channels["range"].astype(np.float32)
    hit = channels["hit"].astype(bool) & np.isfinite(ranges) if "hit" in channels else np.isfinite(ranges)
    elevation, azimuth = channels["elevation"].astype(np.float64), channels["azimuth"].astype(np.float64)
    for name, angles, bound, allowed in (
        ("elevation", elevation, np.pi / 2, "+-pi/2"),
        ("azimuth", azimuth, np.pi, "+-pi"),
    ):
        beyond = np.abs(angles) > bound + ANGLE_TOLERANCE  # (NaN directions are check_values')
        if beyond.any():
            pixel = [int(i) for i in np.unravel_index(int(np.argmax(beyond)), beyond.shape)]
            raise LogFormatError(
                f"{path}: channel {name!r} at pixel {pixel} is {angles[tuple(pixel)]:g} rad; range images hold "
                f"{name} angles within {allowed} rad: the image is damaged or was written by another program"
            )
    cos_el = np.cos(elevation)
    directions = np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), np.sin(elevation)], axis=-1)
    origins = None
    if all(f"origin.{a}" in channels for a in "xyz"):
        origins = np.stack([channels[f"origin.{a}"] for a in "xyz"], axis=-1)[None]
    times = start + channels.get("time", np.zeros_like(ranges)).astype(np.float64)
    return Log(
        poses=pose[None],
        directions=directions[None],
        origins=origins,
        ranges=np.where(hit, ranges, np.nan)[None],
        hit=hit[None],
        times=times[None],
        attributes={k[len("attr.") :]: v[None] for k, v in channels.items() if k.startswith("attr.")},
        sensor={**sensor, "source": str(path)},
    )
