"""Ouster sensors: the one reader of Ouster metadata JSON, the vendor's beam geometry, and OS-1 patterns.

:func:`read_ouster_metadata` is mi-lidar's only parser of Ouster metadata and :func:`beam_rays` its only
copy of the vendor's ray geometry: the firing pattern (:func:`ouster`) and the pcap decoder
(:mod:`mi_lidar.io.ouster`) both use them, so a simulated range compares ray by ray with a decoded one.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import PatternError, unreadable
from mi_lidar.core.patterns.firing import TWO_PI, FiringPattern, positive_float, positive_int
from mi_lidar.core.patterns.vendor import (
    OS1_BEAM_ORIGIN_MM,
    OS1_GEN1_ALTITUDE_SPAN_DEG,
    OS1_GEN1_AZIMUTH_CYCLE_DEG,
    OS1_LIDAR_TO_SENSOR,
)

MAX_COLUMNS = 8192
"""Most columns per frame a metadata file may declare (Ouster sensors have at most 2048)."""
MAX_BEAMS = 512
"""Most beams a metadata file may declare (Ouster sensors have at most 128)."""
ANGLE_LIMITS_DEG = {"beam_altitude_angles": 90.0, "beam_azimuth_angles": 180.0}
"""Largest ``|angle|`` (degrees) of each per-beam angle list: a beam above the zenith, or an azimuth offset beyond
half a turn (the same direction as one within it), is a damaged number."""

# Where fields live: the legacy flat layout keeps them at the top level, the newer one in sections.
_SECTIONS = (
    "beam_intrinsics",
    "lidar_intrinsics",
    "lidar_data_format",
    "data_format",
    "config_params",
    "sensor_info",
)
_REQUIRED = object()


@dataclass(frozen=True, eq=False)
class OusterMetadata:
    """What mi-lidar reads of an Ouster sensor's metadata JSON.

    Attributes:
        altitude_deg: (H,) float64 beam altitude angles, degrees, in the file's pixel order.
        azimuth_deg: (H,) float64 beam azimuth offsets, degrees.
        beam_origin_mm: Lidar origin to beam origin distance ``n``, mm (0 when absent).
        lidar_to_sensor: (4, 4) float64 rigid transform, translation in mm (identity when absent).
        pixel_shift_by_row: (H,) int64 destaggering shifts, columns, or None when absent.
        columns_per_frame: Columns per frame ``W``.
        columns_per_packet: Columns per UDP lidar packet (16 when absent).
        profile: UDP lidar profile name (``"LEGACY"`` when absent).
        frequency_hz: Rotation rate, Hz (from ``lidar_mode``, e.g. ``"1024x10"``; 10 when absent).
        product: Product line, e.g. ``"OS-1-32-G"`` (empty when absent).
    """

    altitude_deg: np.ndarray
    azimuth_deg: np.ndarray
    beam_origin_mm: float
    lidar_to_sensor: np.ndarray
    pixel_shift_by_row: np.ndarray | None
    columns_per_frame: int
    columns_per_packet: int
    profile: str
    frequency_hz: float
    product: str

    @property
    def pixels_per_column(self) -> int:
        """Number of beams ``H``."""
        return len(self.altitude_deg)


def read_ouster_metadata(path: str | os.PathLike) -> OusterMetadata:
    """Read an Ouster sensor metadata JSON, legacy flat layout or the newer nested one.

    Args:
        path: The metadata file, e.g. ``../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.json``.

    Returns:
        The metadata, checked: one altitude, azimuth (and shift) per beam, at most
        :data:`MAX_BEAMS` beams of finite angles within :data:`ANGLE_LIMITS_DEG`, shifts of at
        most :data:`MAX_COLUMNS`, 1 to :data:`MAX_COLUMNS` columns per frame, a rigid lidar-to-sensor transform.

    Raises:
        PatternError: The file is missing, not JSON, or lacks or contradicts a field (named).
    """
    where = f"ouster metadata {os.fspath(path)}"
    try:
        meta = json.loads(Path(path).read_text(encoding="utf-8"))
    except PermissionError as exc:  # (its fix was to pass the metadata JSON: the user had)
        raise unreadable(os.fspath(path), "Ouster metadata", PatternError) from exc
    except OSError as exc:
        raise PatternError(
            f"cannot read Ouster metadata {os.fspath(path)!r} ({exc.strerror}); pass the "
            "sensor's metadata JSON, e.g. ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.json"
        ) from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise PatternError(
            f"{where} is not valid JSON ({exc}); pass the metadata JSON written by the sensor or the Ouster SDK"
        ) from exc
    if not isinstance(meta, dict):
        raise PatternError(f"{where}: expected a JSON object, got {type(meta).__name__}")
    sections = [meta] + [meta[key] for key in _SECTIONS if isinstance(meta.get(key), dict)]

    def find(key: str, default=_REQUIRED):
        for section in sections:
            if key in section:
                return section[key]
        if default is _REQUIRED:
            raise PatternError(f"{where}: missing field {key!r}; the file is not Ouster sensor metadata")
        return default

    def angles(key: str) -> np.ndarray:
        value = find(key)
        try:
            values = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise PatternError(f"{where}: {key!r} must be a list of degrees") from exc
        if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
            raise PatternError(f"{where}: {key!r} must be a non-empty list of finite degrees, got {value!r}")
        beyond = np.abs(values) > ANGLE_LIMITS_DEG[key]
        if beyond.any():
            i = int(np.argmax(beyond))
            raise PatternError(
                f"{where}: {key}[{i}] is {values[i]:g} degrees; beam angles there lie within "
                f"+-{ANGLE_LIMITS_DEG[key]:g} degrees: the metadata is corrupt, use the JSON the sensor wrote"
            )
        return values

    altitude_deg = angles("beam_altitude_angles")
    azimuth_deg = angles("beam_azimuth_angles")
    if altitude_deg.size != azimuth_deg.size:
        raise PatternError(
            f"{where}: {altitude_deg.size} beam_altitude_angles but {azimuth_deg.size} "
            "beam_azimuth_angles; the metadata is corrupt"
        )
    if altitude_deg.size > MAX_BEAMS:
        raise PatternError(f"{where}: {altitude_deg.size} beams; the metadata may describe at most {MAX_BEAMS}")
    lidar_mode = str(find("lidar_mode", ""))
    mode = re.fullmatch(r"(\d+)x(\d+)", lidar_mode)
    columns = find("columns_per_frame", int(mode.group(1)) if mode else None)
    if isinstance(columns, bool) or not isinstance(columns, int) or not 0 < columns <= MAX_COLUMNS:
        raise PatternError(
            f"{where}: columns_per_frame is {columns!r} and lidar_mode is {lidar_mode!r}; "
            f"the metadata must give the number of columns per frame (1 to {MAX_COLUMNS})"
        )
    frequency_hz = float(mode.group(2)) if mode else 10.0
    if frequency_hz <= 0:
        raise PatternError(f"{where}: lidar_mode {lidar_mode!r} gives no rotation rate; expected e.g. '1024x10'")
    pixels = find("pixels_per_column", altitude_deg.size)
    if pixels != altitude_deg.size:
        raise PatternError(
            f"{where}: pixels_per_column is {pixels!r} but {altitude_deg.size} beam angles are "
            "given; the metadata is corrupt"
        )
    shifts = find("pixel_shift_by_row", None)
    if shifts is not None:
        given = shifts
        shifts = np.asarray(given)
        if shifts.shape != altitude_deg.shape or not np.issubdtype(shifts.dtype, np.integer):
            raise PatternError(f"{where}: pixel_shift_by_row must hold {altitude_deg.size} integers, got {given!r}")
        if np.any(np.abs(shifts) > MAX_COLUMNS):
            i = int(np.argmax(np.abs(shifts) > MAX_COLUMNS))
            raise PatternError(
                f"{where}: pixel_shift_by_row[{i}] is {given[i]}; a shift is a column offset of at most "
                f"{MAX_COLUMNS} (the most columns a frame may have): the metadata is corrupt, use the JSON the sensor "
                "wrote"
            )
        shifts = shifts.astype(np.int64)
    per_packet = positive_int(where, "columns_per_packet", find("columns_per_packet", 16))
    if per_packet > columns:
        raise PatternError(f"{where}: columns_per_packet is {per_packet}, more than the {columns} columns per frame")
    origin_mm = find("lidar_origin_to_beam_origin_mm", 0.0)
    if isinstance(origin_mm, bool) or not isinstance(origin_mm, (int, float)) or not math.isfinite(origin_mm):
        raise PatternError(f"{where}: lidar_origin_to_beam_origin_mm must be a number of mm, got {origin_mm!r}")
    return OusterMetadata(
        altitude_deg=altitude_deg,
        azimuth_deg=azimuth_deg,
        beam_origin_mm=float(origin_mm),
        lidar_to_sensor=_rigid_transform(where, find("lidar_to_sensor_transform", np.eye(4).ravel().tolist())),
        pixel_shift_by_row=shifts,
        columns_per_frame=columns,
        columns_per_packet=per_packet,
        profile=str(find("udp_profile_lidar", "LEGACY")),
        frequency_hz=frequency_hz,
        product=str(find("prod_line", "")),
    )


def nominal_metadata(beams: int, columns: int) -> OusterMetadata:
    """The metadata of a nominal OS-1 (gen 1 intrinsics of the Ouster SDK, see :func:`ouster`).

    Args:
        beams: Number of beams H.
        columns: Columns per frame W.

    Returns:
        Metadata named ``"os1-<beams>"`` at 10 Hz, without pixel shifts.
    """
    return OusterMetadata(
        altitude_deg=np.linspace(*OS1_GEN1_ALTITUDE_SPAN_DEG, beams),
        azimuth_deg=np.resize(np.asarray(OS1_GEN1_AZIMUTH_CYCLE_DEG), beams),
        beam_origin_mm=OS1_BEAM_ORIGIN_MM,
        lidar_to_sensor=np.asarray(OS1_LIDAR_TO_SENSOR),
        pixel_shift_by_row=None,
        columns_per_frame=columns,
        columns_per_packet=16,
        profile="LEGACY",
        frequency_hz=10.0,
        product=f"os1-{beams}",
    )


def beam_rays(meta: OusterMetadata, measurement: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray directions and origins of Ouster pixels in the sensor frame, by the vendor's geometry.

    Pixel ``(u, v)`` is beam ``u`` (the metadata's pixel order) at measurement id
    ``m = measurement[u, v]``, fired at encoder angle ``enc = 2 pi (1 - m / W)``. In the lidar
    frame it points along ``d = (cos(enc - az) cos alt, sin(enc - az) cos alt, sin alt)`` and
    its range counts from ``n (cos enc, sin enc, 0) - n d`` (``n`` the beam origin distance);
    both are then mapped through ``lidar_to_sensor``. ``cos(enc - az)`` and ``sin(enc - az)``
    come from per-column and per-beam tables by the angle-sum identities, so no trigonometry
    runs per pixel.

    Args:
        meta: The sensor's metadata.
        measurement: (H, W) integer measurement ids in [0, W).

    Returns:
        ``(direction, origin)``: (H, W, 3) float64 unit directions and (H, W, 3) float64
        origins in m, so ``origin + range * direction`` is the SDK's Cartesian point.
    """
    height, width = meta.pixels_per_column, meta.columns_per_frame
    encoder = TWO_PI * (1 - np.arange(width) / width)
    cos_e, sin_e = np.cos(encoder)[measurement], np.sin(encoder)[measurement]
    azimuth = -np.radians(meta.azimuth_deg)[:, None]
    altitude = np.radians(meta.altitude_deg)[:, None]
    cos_alt, sin_alt = np.cos(altitude), np.sin(altitude)
    cos_ea = cos_e * np.cos(azimuth) - sin_e * np.sin(azimuth)
    sin_ea = sin_e * np.cos(azimuth) + cos_e * np.sin(azimuth)
    n = meta.beam_origin_mm
    rotation, translation = meta.lidar_to_sensor[:3, :3], meta.lidar_to_sensor[:3, 3]
    # Beam origin n (cos enc, sin enc, 0) minus n * direction, then the lidar-to-sensor transform;
    # rotations are written out elementwise (BLAS threads would compete with Dr.Jit's).
    d = (cos_ea * cos_alt, sin_ea * cos_alt, np.broadcast_to(sin_alt, (height, width)))
    o = (n * (cos_e - d[0]), n * (sin_e - d[1]), -n * d[2])
    direction = np.stack([rotation[i, 0] * d[0] + rotation[i, 1] * d[1] + rotation[i, 2] * d[2] for i in range(3)], -1)
    origin = np.stack(
        [
            (rotation[i, 0] * o[0] + rotation[i, 1] * o[1] + rotation[i, 2] * o[2] + translation[i]) / 1000.0
            for i in range(3)
        ],
        -1,
    )
    return direction, origin


def destagger(image: np.ndarray, pixel_shift_by_row) -> np.ndarray:
    """Staggered (..., H, W) image (columns = measurement ids) -> destaggered (azimuth-aligned)."""
    shift = np.asarray(pixel_shift_by_row)
    width = image.shape[-1]
    columns = (np.arange(width)[None, :] - shift[:, None]) % width
    return np.take_along_axis(image, np.broadcast_to(columns, image.shape), axis=-1)


def restagger(image: np.ndarray, pixel_shift_by_row) -> np.ndarray:
    """Inverse of :func:`destagger`: back to the packet (measurement id) column order."""
    return destagger(image, -np.asarray(pixel_shift_by_row))


def ouster(
    metadata: str | os.PathLike | None = None,
    beams: int | None = None,
    columns: int | None = None,
    rpm: float | None = None,
    destaggered: bool = True,
) -> FiringPattern:
    """An Ouster OS-1 from its metadata JSON, or a nominal OS-1-32/64/128.

    Geometry follows Ouster's manual and SDK. In the sensor's *lidar frame*, measurement
    ``mid`` of a frame of ``W`` columns has encoder angle ``enc = 2 pi (1 - mid / W)``; beam
    ``i`` points along ``d = (cos(enc - az_i) cos alt_i, sin(enc - az_i) cos alt_i, sin alt_i)``
    (``az_i``, ``alt_i`` from ``beam_azimuth_angles`` and ``beam_altitude_angles``) and leaves
    the beam origin ``n (cos enc, sin enc, 0)``, ``n = lidar_origin_to_beam_origin_mm``. The
    reported range ``r`` counts from ``n`` before the beam origin, so the ray origin is
    ``n (cos enc, sin enc, 0) - n d`` and ``origin + r * direction`` is the SDK's Cartesian
    point. Directions and origins are then mapped to Ouster's *sensor frame* (x forward, y
    left, z up, as published by ouster-ros) through ``lidar_to_sensor_transform``: a half
    turn about z and 36.18 mm up on OS-1 units. This matches :mod:`mi_lidar.io.ouster`, so a
    simulated range compares ray by ray with a decoded one. All beams of a column fire
    together, at ``mid * period / W``.

    Rows are sorted by altitude (highest first; ``beam_id`` gives the metadata's pixel
    index). With ``destaggered=True`` the columns form the range image of Ouster's
    ``destagger``: pixel ``(i, j)`` holds measurement ``mid = (j - shift_i) mod W`` with
    ``shift_i = pixel_shift_by_row[i]``, so every column looks in about the same direction;
    with ``destaggered=False`` column ``j`` is measurement id ``j``. Column 0 looks
    backwards and the middle column forward, as for :func:`spinning`.

    Without a file the nominal tables are used: the 64 OS-1 gen 1 intrinsics of the Ouster
    SDK (altitudes uniform over +-16.611 deg, azimuth offsets cycling 3.164, 1.055, -1.055,
    -3.164 deg, n = 12.163 mm, the SDK's default lidar-to-sensor transform); OS-1-32 and
    OS-1-128 get the same span and stagger with uniform spacing, since no per-beam table is
    published for them (later OS1 revisions see up to +-22.5 deg: pass the unit's metadata
    for exact angles). Pixel shifts are then ``round((az_i - min az) * W / 360 deg)``, the
    rule that reproduces Ouster's tables.

    Args:
        metadata: Path of the sensor metadata JSON (legacy flat layout as in
            ``../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.json``, or the newer layout
            with ``beam_intrinsics`` and ``lidar_data_format``), or None for nominal tables.
        beams: Number of beams; None takes it from the metadata (nominal default 32). With a
            file it must match ``pixels_per_column``; nominal tables exist for 32, 64, 128.
        columns: Columns per frame W; None takes ``columns_per_frame`` from the metadata
            (nominal default 1024). With a file it must match the metadata.
        rpm: Rotor speed, rev/min; None takes it from ``lidar_mode`` (e.g. ``"1024x10"`` is
            600 rpm), else 600.
        destaggered: Range-image layout (True) or measurement-id layout (False).

    Returns:
        A (beams, columns) pattern with ray origins, named ``"os1-<beams>"`` or after the
        metadata's product line.

    Raises:
        PatternError: Unreadable or incomplete metadata, values that contradict it, or
            parameters out of range.
    """
    where = "ouster"
    if metadata is None:
        h = 32 if beams is None else positive_int(where, "beams", beams)
        if h not in (32, 64, 128):
            raise PatternError(
                f"{where}: no nominal table for beams={beams!r}; choose 32, 64 or 128, "
                "or pass the sensor's metadata JSON"
            )
        meta = nominal_metadata(h, 1024 if columns is None else positive_int(where, "columns", columns))
    else:
        meta = read_ouster_metadata(metadata)
        if beams is not None and beams != meta.pixels_per_column:
            raise PatternError(
                f"{where}: beams={beams!r} but {metadata} describes {meta.pixels_per_column} beams; "
                "leave beams=None to use the metadata"
            )
        if columns is not None and columns != meta.columns_per_frame:
            raise PatternError(
                f"{where}: columns={columns!r} but {metadata} has {meta.columns_per_frame} columns per frame; "
                "leave columns=None to use the metadata"
            )
    h, w = meta.pixels_per_column, meta.columns_per_frame
    period = 60.0 / (60.0 * meta.frequency_hz if rpm is None else positive_float(where, "rpm", rpm))
    shifts = meta.pixel_shift_by_row
    if shifts is None:
        shifts = np.rint((meta.azimuth_deg - meta.azimuth_deg.min()) * w / 360.0).astype(np.int64)
    mid = np.broadcast_to(np.arange(w), (h, w))
    if destaggered:
        mid = destagger(mid, shifts)
    order = np.argsort(-meta.altitude_deg, kind="stable")
    direction, origin = beam_rays(meta, mid)
    direction, origin, mid = direction[order], origin[order], mid[order]
    return FiringPattern(
        name=meta.product.lower() or f"ouster-{h}",
        elevation=np.arcsin(np.clip(direction[..., 2], -1.0, 1.0)),
        azimuth=np.arctan2(direction[..., 1], direction[..., 0]),
        time=mid * (period / w),
        period=period,
        origin=origin,
        beam_id=order,
    )


def _rigid_transform(where: str, value) -> np.ndarray:
    """A 16-number row-major rigid transform as a (4, 4) float64 array, else PatternError."""
    try:
        matrix = np.asarray(value, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError) as exc:
        raise PatternError(
            f"{where}: lidar_to_sensor_transform must be 16 numbers (row-major 4 x 4), got {value!r}"
        ) from exc
    rotation = matrix[:3, :3]
    rigid = (
        np.all(np.isfinite(matrix))
        and np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
        and np.linalg.det(rotation) > 0
        and np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0])
    )
    if not rigid:
        raise PatternError(
            f"{where}: lidar_to_sensor_transform {value!r} is not a rigid transform; the metadata is corrupt"
        )
    return matrix
