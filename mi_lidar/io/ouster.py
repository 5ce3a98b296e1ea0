"""Ouster lidar pcap captures + sensor metadata JSON -> :class:`~mi_lidar.core.log.Log`.

Supported UDP lidar profiles: ``LEGACY`` (firmware <= 2.1), ``RNG19_RFL8_SIG16_NIR16``,
``RNG19_RFL8_SIG16_NIR16_DUAL`` and ``RNG15_RFL8_NIR8``. Metadata may be the legacy flat JSON
(``beam_altitude_angles`` at top level, ``data_format``) or the newer nested one
(``beam_intrinsics``, ``lidar_intrinsics``, ``lidar_data_format``, ``config_params``); it is read, and
the rays are placed, by the same core functions the Ouster firing pattern uses
(:mod:`mi_lidar.core.patterns.ouster_sensor`).

The log is **destaggered**: row ``u`` is beam ``u`` (top row = highest beam), column ``v`` is an
azimuth bin, and pixel ``(u, v)`` holds the measurement of column
``(v - pixel_shift_by_row[u]) mod W`` of the packet stream (the measurement id). Every pixel's
direction, origin and time follow the vendor's geometry exactly: with encoder angle
``enc = 2 pi (1 - m / W)`` for measurement id ``m``, beam azimuth ``az`` and altitude ``alt``,

    direction = (cos(enc - az) cos(alt), sin(enc - az) cos(alt), sin(alt))
    origin    = n (cos enc, sin enc, 0) - n direction          (n = lidar_origin_to_beam_origin)

both mapped through ``lidar_to_sensor_transform``, so ``origin + range * direction`` is the
SDK's Cartesian point and ``ranges`` are the sensor's reported ranges (m), not shortened by
``n``. Range 0 (no return), columns missing from the capture and columns whose status flags them
invalid are misses (``hit`` False, range NaN); ``attributes['valid']`` is False for the last two.

Attributes (S, H, W): ``range_mm`` (uint32, the raw masked range in mm), ``reflectivity``,
``signal``, ``near_ir`` (and ``range2_mm``, ``reflectivity2``, ``signal2`` for the dual profile),
``valid``. Use :func:`restagger` on ``range_mm`` to get the SDK's ``LidarScan.field(RANGE)``
array, whose MD5 is the vendor digest.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError, PatternError
from mi_lidar.core.log import Log
from mi_lidar.core.patterns.ouster_sensor import OusterMetadata, beam_rays, destagger, read_ouster_metadata, restagger
from mi_lidar.io._pcap import read_udp


@dataclass(frozen=True)
class _Field:
    """One per-pixel field: byte offset in the pixel block, dtype, bit mask, left shift."""

    offset: int
    dtype: str
    mask: int = 0
    shift: int = 0

    @property
    def stored(self) -> str:
        """The dtype decoded values are kept in: at least 16 bits, wide enough for the shifted mask
        (low-bandwidth ranges in 8 mm units reach 0x7FFF << 3 = 262 136 mm)."""
        largest = (self.mask or (1 << (8 * np.dtype(self.dtype).itemsize)) - 1) << self.shift
        return "<u2" if largest <= 0xFFFF else "<u4"


@dataclass(frozen=True)
class _Profile:
    """Byte layout of one UDP lidar profile (sizes in bytes)."""

    packet_header: int
    column_header: int
    pixel: int
    column_footer: int
    packet_footer: int
    fields: dict


PROFILES = {
    "LEGACY": _Profile(
        0,
        16,
        12,
        4,
        0,
        {
            "range_mm": _Field(0, "<u4", 0x000FFFFF),
            "reflectivity": _Field(4, "<u2"),
            "signal": _Field(6, "<u2"),
            "near_ir": _Field(8, "<u2"),
        },
    ),
    "RNG19_RFL8_SIG16_NIR16": _Profile(
        32,
        12,
        12,
        0,
        32,
        {
            "range_mm": _Field(0, "<u4", 0x0007FFFF),
            "reflectivity": _Field(4, "u1"),
            "signal": _Field(6, "<u2"),
            "near_ir": _Field(8, "<u2"),
        },
    ),
    "RNG19_RFL8_SIG16_NIR16_DUAL": _Profile(
        32,
        12,
        16,
        0,
        32,
        {
            "range_mm": _Field(0, "<u4", 0x0007FFFF),
            "reflectivity": _Field(3, "u1"),
            "range2_mm": _Field(4, "<u4", 0x0007FFFF),
            "reflectivity2": _Field(7, "u1"),
            "signal": _Field(8, "<u2"),
            "signal2": _Field(10, "<u2"),
            "near_ir": _Field(12, "<u2"),
        },
    ),
    "RNG15_RFL8_NIR8": _Profile(
        32,
        12,
        4,
        0,
        32,
        {
            "range_mm": _Field(0, "<u2", 0x7FFF, 3),
            "reflectivity": _Field(2, "u1"),
            "near_ir": _Field(3, "u1", 0, 4),
        },
    ),
}


def _decoder_metadata(path: Path) -> OusterMetadata:
    """The sensor's metadata (:func:`~mi_lidar.core.patterns.ouster_sensor.read_ouster_metadata`), with
    what decoding packets needs besides: the destaggering shifts and a supported UDP profile.

    Raises:
        LogFormatError: Unreadable or inconsistent metadata (the field named), no
            ``pixel_shift_by_row``, or an unsupported profile.
    """
    try:
        meta = read_ouster_metadata(path)
    except PatternError as exc:
        raise LogFormatError(str(exc)) from exc
    if meta.pixel_shift_by_row is None:
        raise LogFormatError(
            f"{path}: missing field 'pixel_shift_by_row'; the capture cannot be destaggered without it"
        )
    if meta.profile not in PROFILES:
        raise LogFormatError(f"{path}: udp_profile_lidar {meta.profile!r}; supported: {', '.join(PROFILES)}")
    return meta


def range_digest(log: Log, scan: int = 0) -> str:
    """MD5 hex digest of the SDK's RANGE field of one scan of an Ouster log.

    The vendor digest (``scans[i].RANGE`` in ``*_digest.json``) is over the **staggered**
    (H, W) C-order uint32 array of masked ranges in mm, columns indexed by measurement id.
    """
    staggered = restagger(log.attributes["range_mm"][scan], log.sensor["pixel_shift_by_row"])
    return hashlib.md5(np.ascontiguousarray(staggered, dtype=np.uint32).tobytes()).hexdigest()


def _take(block: np.ndarray, spec: _Field) -> np.ndarray:
    """Decode field ``spec`` from the last axis (bytes) of ``block``."""
    size = np.dtype(spec.dtype).itemsize
    raw = np.ascontiguousarray(block[..., spec.offset : spec.offset + size]).view(spec.dtype)[..., 0]
    values = raw.astype(spec.stored)
    if spec.mask:
        values &= spec.mask
    if spec.shift:
        values <<= spec.shift
    return values


def read_ouster(
    path: str | os.PathLike,
    metadata: str | os.PathLike | None = None,
) -> Log:
    """Decode every frame of an Ouster lidar pcap into a destaggered log.

    Args:
        path: The ``.pcap`` capture (UDP lidar packets; IMU packets are skipped).
        metadata: The sensor metadata ``.json``; defaults to ``path`` with suffix ``.json``.

    Returns:
        A log with one scan per frame id in capture order (``H`` = pixels per column, ``W`` =
        columns per frame); see the module docstring for the layout and attributes. Partial
        frames (capture started or ended mid-rotation) are kept: their absent columns have
        ``valid`` False and ``hit`` False. Poses are identity (the capture holds none).

    Raises:
        LogFormatError: Unreadable pcap or metadata, no packet of the size the profile implies
            (wrong profile or metadata), or a measurement id outside the frame.
    """
    path = Path(path)
    metadata = Path(metadata) if metadata is not None else path.with_suffix(".json")
    meta = _decoder_metadata(metadata)
    profile = PROFILES[meta.profile]
    height, width, per_packet = meta.pixels_per_column, meta.columns_per_frame, meta.columns_per_packet
    column_size = profile.column_header + height * profile.pixel + profile.column_footer
    packet_size = profile.packet_header + per_packet * column_size + profile.packet_footer
    udp = read_udp(path)
    data, _, offsets = udp.select(None, packet_size)
    if len(data) == 0:
        sizes = sorted({len(p) for p in udp.payloads})
        raise LogFormatError(
            f"{path}: no {packet_size}-byte lidar packets (profile {meta.profile}, {height} beams, "
            f"{per_packet} columns per packet per {metadata.name}); UDP payload sizes found: {sizes[:8]}. "
            "Check that the metadata JSON belongs to this capture."
        )
    columns = data[:, profile.packet_header : profile.packet_header + per_packet * column_size]
    columns = columns.reshape(len(data), per_packet, column_size)
    stamp = np.ascontiguousarray(columns[..., 0:8]).view("<u8")[..., 0]
    measurement = _take(columns, _Field(8, "<u2"))
    if meta.profile == "LEGACY":
        frame = _take(columns, _Field(10, "<u2"))
        status = np.ascontiguousarray(columns[..., -4:]).view("<u4")[..., 0]
    else:
        frame = np.broadcast_to(_take(data, _Field(2, "<u2"))[:, None], measurement.shape)
        status = _take(columns, _Field(10, "<u2"))
    bad = measurement >= width
    if bad.any():
        packet = int(np.argmax(bad.any(axis=1)))
        raise LogFormatError(
            f"{path}: packet at byte {offsets[packet]}: measurement id {int(measurement[bad][0])} >= "
            f"{width} columns per frame ({metadata.name}); wrong metadata or corrupt packet"
        )
    pixels = columns[..., profile.column_header : profile.column_header + height * profile.pixel]
    pixels = pixels.reshape(len(data), per_packet, height, profile.pixel)

    frame, measurement, stamp = frame.ravel(), measurement.ravel().astype(np.int64), stamp.ravel()
    valid_column = (status.ravel() & 1).astype(bool)
    scan = np.concatenate([[0], np.cumsum(frame[1:] != frame[:-1])])
    n_scans = int(scan[-1]) + 1

    # Scatter every column straight to its destaggered place: row u of measurement id m lands in
    # column (m + pixel_shift_by_row[u]) mod W.
    shift = meta.pixel_shift_by_row
    rows = np.arange(height)[None, :]
    cells = (scan[:, None], rows, (measurement[:, None] + np.asarray(shift)[None, :]) % width)
    fields = {}
    for name, spec in profile.fields.items():
        image = np.zeros((n_scans, height, width), dtype=spec.stored)
        image[cells] = _take(pixels, spec).reshape(-1, height)
        fields[name] = image
    valid = np.zeros((n_scans, height, width), dtype=bool)
    valid[cells] = valid_column[:, None]
    fields["range_mm"][~valid] = 0

    period = 1.0 / meta.frequency_hz
    seconds = stamp.astype(np.float64) * 1e-9
    start = np.full(n_scans, np.nan)
    np.fmin.at(start, scan, seconds - measurement * period / width)
    times = start[:, None, None] + (np.arange(width) * period / width)[None, None, :]
    times = destagger(np.broadcast_to(times, (n_scans, height, width)), shift)
    times[cells] = seconds[:, None]

    direction, origin = beam_rays(meta, destagger(np.broadcast_to(np.arange(width), (height, width)), shift))
    hit = valid & (fields["range_mm"] > 0)
    ranges = np.where(hit, fields["range_mm"] / 1000.0, np.nan)
    sensor = {
        "name": f"ouster:{meta.product or 'ouster'}",
        "source": str(path),
        "metadata": str(metadata),
        "profile": meta.profile,
        "pixel_shift_by_row": shift.tolist(),
        "columns_per_frame": width,
        "frequency_hz": meta.frequency_hz,
        "frame_ids": [int(f) for f in frame[np.r_[0, np.flatnonzero(np.diff(scan)) + 1]]],
        "beam_altitude_deg": meta.altitude_deg.tolist(),
        "beam_azimuth_deg": meta.azimuth_deg.tolist(),
        "layout": "destaggered",
        "range_unit": "m",
    }
    return Log(
        poses=np.tile(np.eye(4), (n_scans, 1, 1)),
        directions=direction[None],
        origins=origin[None],
        ranges=ranges,
        hit=hit,
        times=times,
        attributes={**fields, "valid": valid},
        sensor=sensor,
    )
