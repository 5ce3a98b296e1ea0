"""Velodyne VLP-16, VLP-32C and HDL-32E pcap captures (+ calibration) -> :class:`~mi_lidar.core.log.Log`.

Each 1206-byte data packet holds 12 blocks ``[0xFFEE, azimuth * 100 (u16), 32 x (distance u16 in
resolution units, reflectivity u8)]``, a u32 timestamp (us past the hour), a return-mode byte
(0x37 strongest, 0x38 last, 0x39 dual) and a product byte. The VLP-16 fires two 16-laser
sequences per block; the 32-laser sensors one sequence per block. In dual-return mode blocks come
in pairs with the same azimuth: even blocks hold the last return, odd blocks the strongest.

Geometry follows the ROS ``velodyne_pointcloud`` driver (ROS frame: x forward, y left, z up):
every firing's azimuth is interpolated in time between block azimuths at the laser's own firing
time (vendor timing tables), ``alpha = azimuth - rot_correction``, ``omega = vert_correction``,

    direction = (cos(omega) cos(alpha), -cos(omega) sin(alpha), sin(omega))

the range is ``distance * resolution + dist_correction`` (m), and the (usually zero) vertical and
horizontal beam offsets become per-ray origins. Distance 0 is a miss.

Layout: rows are lasers sorted by elevation, highest first (``attributes['laser_id']`` keeps the
ids); columns are firing sequences in time order. Frames are split where the azimuth crosses
``cut_azimuth_deg``; frames of different length are padded at the end with cells whose
``attributes['valid']`` is False (their direction and time are extrapolated from the rotation).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError, parser_message
from mi_lidar.core.log import Log
from mi_lidar.core.patterns.vendor import HDL32E, VLP16, VLP32C, SpinningTable
from mi_lidar.io._pcap import read_udp

PACKET_SIZE = 1206
DATA_PORT = 2368
BLOCKS = 12
BLOCK_FLAG = 0xEEFF  # bytes FF EE read as little-endian u16
RETURN_MODES = {0x37: "strongest", 0x38: "last", 0x39: "dual"}
PRODUCT_IDS = {0x21: "HDL-32E", 0x22: "VLP-16", 0x24: "VLP-16", 0x28: "VLP-32C"}
TIMING_TOLERANCE = 0.15
MAX_CORRECTION_M = 10.0  # a distance or offset correction beyond this is a unit slip (tables in m; db.xml has cm)
CORRECTION_LIMITS = {  # calibration column -> (|value| must stay below, what the message says it must be)
    "vert_correction": (np.pi / 2, "a finite angle in radians within +-pi/2 (degrees given by mistake?)"),
    "rot_correction": (np.pi, "a finite angle in radians within +-pi (degrees given by mistake?)"),
    **dict.fromkeys(
        ("dist_correction", "vert_offset_correction", "horiz_offset_correction"),
        (MAX_CORRECTION_M, f"a finite length in metres within +-{MAX_CORRECTION_M:g} m (cm or mm given by mistake?)"),
    ),
}
ELEVATION_TOLERANCE_DEG = 1.0


@dataclass(frozen=True)
class Model:
    """One Velodyne model as its packets see it: the core's laser table plus the packet layout.

    Attributes:
        name: The vendor's name (``"VLP-16"``), as :data:`PRODUCT_IDS` and ``--model`` spell it.
        table: Laser angles and firing timing (:mod:`mi_lidar.core.patterns.vendor`, the same table
            the simulated pattern of this sensor uses).
        sequences_per_block: Firing sequences per data block (2 for the VLP-16, 1 for 32 lasers).
        resolution_m: Distance unit of the packets (m).
    """

    name: str
    table: SpinningTable
    sequences_per_block: int
    resolution_m: float

    @property
    def lasers(self) -> int:
        return len(self.table.elevation_deg)

    @property
    def sequence_us(self) -> float:
        """Duration of one firing sequence (us)."""
        return self.table.cycle_s * 1e6

    @property
    def laser_us(self) -> np.ndarray:
        """(L,) firing time of each laser within its sequence (us)."""
        return np.asarray(self.table.firing_offset_s) * 1e6

    @property
    def elevation_deg(self) -> np.ndarray:
        return np.asarray(self.table.elevation_deg, float)

    @property
    def azimuth_offset_deg(self) -> np.ndarray:
        return np.asarray(self.table.azimuth_offset_deg, float)

    def packet_us(self, mode: str) -> float:
        """Time between data packets (us): 12 firings per packet, 6 in ``"dual"`` return mode."""
        return (BLOCKS // 2 if mode == "dual" else BLOCKS) * self.sequence_us * self.sequences_per_block


MODELS = {
    model.name: model
    for model in (
        Model("VLP-16", VLP16, 2, 0.002),
        Model("HDL-32E", HDL32E, 1, 0.002),
        Model("VLP-32C", VLP32C, 1, 0.004),
    )
}


@dataclass
class Calibration:
    """Per-laser corrections (ROS ``velodyne_pointcloud`` YAML conventions).

    Attributes:
        vert: (L,) elevation angles (rad).
        rot: (L,) azimuth corrections (rad), subtracted from the firing azimuth.
        dist: (L,) range offsets (m).
        vert_offset: (L,) vertical beam-origin offsets (m).
        horiz_offset: (L,) horizontal beam-origin offsets (m).
        resolution_m: Distance unit (m).
    """

    vert: np.ndarray
    rot: np.ndarray
    dist: np.ndarray
    vert_offset: np.ndarray
    horiz_offset: np.ndarray
    resolution_m: float

    @classmethod
    def of_model(cls, model: Model) -> Calibration:
        """The nominal table from the model's manual (no per-unit corrections)."""
        zeros = np.zeros(model.lasers)
        return cls(
            np.radians(model.elevation_deg),
            np.radians(model.azimuth_offset_deg),
            zeros,
            zeros,
            zeros,
            model.resolution_m,
        )


def read_calibration(path: str | os.PathLike) -> Calibration:
    """Read a ``velodyne_pointcloud`` calibration YAML (``lasers:`` list with ``laser_id``,
    ``vert_correction``, ``rot_correction`` in rad, optional offsets in m, optional
    ``distance_resolution``).

    Raises:
        LogFormatError: Unreadable YAML, a missing or non-numeric field (named with the laser),
            laser ids that are not ``0 .. L-1``, or a correction that is not finite or beyond
            :data:`CORRECTION_LIMITS`.
    """
    from ruamel.yaml import YAML, YAMLError

    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such Velodyne calibration file")
    try:
        table = YAML(typ="safe", pure=True).load(path.read_text(encoding="utf-8"))
    except (YAMLError, UnicodeDecodeError, ValueError) as exc:
        raise LogFormatError(
            f"{path}: not readable YAML ({parser_message(exc)}); repair the file or export it again"
        ) from exc
    lasers = table.get("lasers") if isinstance(table, dict) else None
    if not isinstance(lasers, list) or not lasers:
        raise LogFormatError(f"{path}: no 'lasers' list; expected a velodyne_pointcloud calibration")
    count = len(lasers)
    columns = {
        k: np.zeros(count)
        for k in (
            "vert_correction",
            "rot_correction",
            "dist_correction",
            "vert_offset_correction",
            "horiz_offset_correction",
        )
    }
    seen = set()
    for index, laser in enumerate(lasers):
        try:
            laser_id = int(laser["laser_id"])
            if not 0 <= laser_id < count or laser_id in seen:
                raise ValueError(f"laser_id {laser_id} is duplicated or outside 0..{count - 1}")
            seen.add(laser_id)
            for key in columns:
                if key in ("vert_correction", "rot_correction") or key in laser:
                    columns[key][laser_id] = float(laser[key])
        except (KeyError, TypeError, ValueError) as exc:
            raise LogFormatError(f"{path}: lasers[{index}]: bad or missing field ({exc})") from exc
    for key, (bound, allowed) in CORRECTION_LIMITS.items():
        bad = ~(np.abs(columns[key]) < bound)
        if bad.any():
            laser = int(np.argmax(bad))
            raise LogFormatError(f"{path}: laser {laser}: {key} is {columns[key][laser]:g}; it must be {allowed}")
    try:
        resolution = float(table.get("distance_resolution", 0.0))
    except (TypeError, ValueError) as exc:
        raise LogFormatError(f"{path}: distance_resolution is not a number ({exc})") from exc
    return Calibration(
        columns["vert_correction"],
        columns["rot_correction"],
        columns["dist_correction"],
        columns["vert_offset_correction"],
        columns["horiz_offset_correction"],
        resolution,
    )


def table_model(calibration: Calibration) -> Model | None:
    """The model whose nominal elevations a calibration table matches, or None.

    A table matches a model with as many lasers when its sorted ``vert_correction`` angles lie
    within :data:`ELEVATION_TOLERANCE_DEG` of the model's nominal ones (per-unit corrections are
    a few tenths of a degree; the HDL-32E and VLP-32C tables differ by up to 5 degrees).
    """
    measured = np.sort(np.degrees(calibration.vert))
    for model in MODELS.values():
        if (
            model.lasers == len(measured)
            and np.abs(np.sort(model.elevation_deg) - measured).max() <= ELEVATION_TOLERANCE_DEG
        ):
            return model
    return None


def _choose_model(
    path: Path,
    model: str | None,
    calibration: Calibration | None,
    table: str | None,
    product: int,
    mode: str,
    spacing_us: float | None,
) -> tuple[Model, str]:
    """Resolve the sensor model and check that the calibration table fits it.

    Without ``model``, the first of these whose packet timing matches the capture wins: the
    packets' product byte, the model the calibration table's elevations match, the model the
    packet spacing alone implies (some firmware writes another model's product byte).

    Returns:
        ``(model, source)``, ``source`` saying what chose it.
    """
    fitted = None if calibration is None else table_model(calibration)
    timed = lambda m: spacing_us is None or abs(spacing_us / m.packet_us(mode) - 1) <= TIMING_TOLERANCE
    if model is not None:
        if model not in MODELS:
            raise LogFormatError(f"{path}: unknown Velodyne model {model!r}; supported: {', '.join(MODELS)}")
        chosen, source = MODELS[model], f"model={model!r}"
    else:
        hints = (
            [(MODELS[PRODUCT_IDS[product]], f"the packets' product byte 0x{product:02x}")]
            if product in PRODUCT_IDS
            else []
        )
        hints += [(fitted, f"calibration {table}")] if fitted is not None else []
        if spacing_us is not None:
            hints += [(m, f"the packet spacing ({spacing_us:.1f} us)") for m in MODELS.values()]
        chosen, source = next(((m, s) for m, s in hints if timed(m)), (None, ""))
        if chosen is None:
            raise LogFormatError(
                f"{path}: cannot tell the Velodyne model (product byte 0x{product:02x}); "
                f"pass model= (--model) one of {', '.join(MODELS)}"
            )
    if not timed(chosen):
        raise LogFormatError(
            f"{path}: packets are {spacing_us:.1f} us apart but a {chosen.name} in {mode} mode sends one every "
            f"{chosen.packet_us(mode):.1f} us; wrong model or calibration?"
        )
    if calibration is None:
        return chosen, source
    fix = "pass the calibration table of this sensor (--calibration) or the right model= (--model)"
    if len(calibration.vert) != chosen.lasers:
        raise LogFormatError(
            f"{path}: calibration {table} has {len(calibration.vert)} lasers but a {chosen.name} ({source}) has "
            f"{chosen.lasers}; {fix}"
        )
    if fitted is not None and fitted is not chosen:
        raise LogFormatError(
            f"{path}: calibration {table} holds the elevations of a {fitted.name} but {source} says "
            f"{chosen.name}; {fix}"
        )
    if calibration.resolution_m and not np.isclose(calibration.resolution_m, chosen.resolution_m):
        raise LogFormatError(
            f"{path}: calibration {table} has distance_resolution {calibration.resolution_m} m but a "
            f"{chosen.name} reports distances in {chosen.resolution_m} m units (ranges would scale by "
            f"{calibration.resolution_m / chosen.resolution_m:.3g}); {fix}"
        )
    return chosen, source


def _u16(block: np.ndarray, offset: int) -> np.ndarray:
    return np.ascontiguousarray(block[..., offset : offset + 2]).view("<u2")[..., 0]


def read_velodyne(
    path: str | os.PathLike,
    calibration: str | os.PathLike | None = None,
    model: str | None = None,
    return_mode: str = "strongest",
    cut_azimuth_deg: float | None = 0.0,
) -> Log:
    """Decode a Velodyne pcap into one scan per revolution.

    Args:
        path: The ``.pcap`` capture (data port 2368; GPS packets on 8308 are skipped).
        calibration: A ``velodyne_pointcloud`` YAML; the model's nominal table when None.
        model: ``"VLP-16"``, ``"VLP-32C"`` or ``"HDL-32E"``; when None, the packets' product byte,
            else the model the calibration's elevations match, else the one the packet spacing
            implies (the first whose packet timing fits the capture; ``sensor['model_source']``
            says which).
        return_mode: For dual-return captures, which return fills ``ranges``: ``"strongest"`` or
            ``"last"``; the other is kept in ``attributes['range_last' | 'range_strongest']`` (m,
            NaN for none).
        cut_azimuth_deg: Azimuth (deg) at which a new frame starts; None cuts at the capture's
            first azimuth, so the first frame is a complete revolution when the capture has one.

    Returns:
        A log with ``H`` = lasers, ``W`` = the longest frame's firing count, per-scan directions
        and origins, absolute times (s) and attributes ``laser_id``, ``intensity``, ``valid``.

    Raises:
        LogFormatError: Unreadable pcap or calibration, no data packets, a bad block flag (named
            with its packet offset), packet timing inconsistent with the model, or a calibration
            table that does not fit the model (laser count, elevations of another model, or a
            ``distance_resolution`` other than the model's distance unit).
    """
    if return_mode not in ("strongest", "last"):
        raise ValueError(f"read_velodyne: return_mode={return_mode!r}; expected 'strongest' or 'last'")
    path = Path(path)
    calib = read_calibration(calibration) if calibration is not None else None
    udp = read_udp(path)
    data, capture_times, offsets = udp.select(DATA_PORT, PACKET_SIZE)
    if len(data) == 0:
        raise LogFormatError(f"{path}: no {PACKET_SIZE}-byte Velodyne data packets on UDP port {DATA_PORT}")
    mode_byte, product = int(data[0, 1204]), int(data[0, 1205])
    if mode_byte not in RETURN_MODES or np.any(data[:, 1204] != mode_byte):
        bad = int(np.argmax(data[:, 1204] != mode_byte)) if mode_byte in RETURN_MODES else 0
        raise LogFormatError(
            f"{path}: packet at byte {offsets[bad]}: return-mode byte 0x{int(data[bad, 1204]):02x}; expected 0x37, "
            "0x38 or 0x39, the same in every packet"
        )
    stamp_us = np.ascontiguousarray(data[:, 1200:1204]).view("<u4")[:, 0].astype(np.float64)
    spacing_us = float(np.median(np.diff(stamp_us) % 3.6e9)) if len(data) > 1 else None
    table = None if calibration is None else str(calibration)
    sensor_model, model_source = _choose_model(path, model, calib, table, product, RETURN_MODES[mode_byte], spacing_us)
    calib = calib or Calibration.of_model(sensor_model)
    resolution = calib.resolution_m or sensor_model.resolution_m
    dual = RETURN_MODES[mode_byte] == "dual"

    blocks = data[:, :1200].reshape(len(data), BLOCKS, 100)
    flags = _u16(blocks, 0)
    if np.any(flags != BLOCK_FLAG):
        packet, block = np.argwhere(flags != BLOCK_FLAG)[0]
        raise LogFormatError(
            f"{path}: packet at byte {offsets[packet]}, block {block}: flag 0x{int(flags[packet, block]):04x}; "
            "expected 0xFFEE (corrupt packet or not Velodyne data)"
        )
    azimuth = _u16(blocks, 2).astype(np.float64)
    if np.any(azimuth >= 36000):
        packet = int(np.argmax((azimuth >= 36000).any(axis=1)))
        raise LogFormatError(f"{path}: packet at byte {offsets[packet]}: block azimuth >= 36000 (0.01 deg units)")
    channels = blocks[:, :, 4:].reshape(len(data), BLOCKS, 32, 3)
    distance = _u16(channels, 0)
    reflectivity = channels[..., 2]

    hour = np.round((capture_times - stamp_us * 1e-6) / 3600.0) * 3600.0
    packet_time = hour + stamp_us * 1e-6
    firings_per_packet = BLOCKS // 2 if dual else BLOCKS
    block_us = sensor_model.sequence_us * sensor_model.sequences_per_block

    # Firings in time order: (P, F, sequences, lasers) with F = blocks (single) or block pairs (dual).
    lasers, per_block = sensor_model.lasers, sensor_model.sequences_per_block
    if dual:
        pick = 1 if return_mode == "strongest" else 0
        other_distance = distance[:, 1 - pick :: 2]
        distance, reflectivity, azimuth = distance[:, pick::2], reflectivity[:, pick::2], azimuth[:, pick::2]
    shape = (len(data), firings_per_packet * per_block, lasers)
    distance, reflectivity = distance.reshape(shape), reflectivity.reshape(shape)
    firing = np.arange(firings_per_packet)
    block_time = packet_time[:, None] + firing[None, :] * block_us * 1e-6
    column_time = (block_time[:, :, None] + np.arange(per_block) * sensor_model.sequence_us * 1e-6).reshape(-1)

    # Unwrapped block azimuth (deg) as a function of time, extrapolated linearly at the ends.
    knots_t, knots_a = block_time.reshape(-1), np.unwrap(azimuth.reshape(-1) / 100.0, period=360.0)
    span = knots_t[-1] - knots_t[0]
    rate = (knots_a[-1] - knots_a[0]) / span if span > 0 else 360.0 * 10

    def azimuth_at(t: np.ndarray) -> np.ndarray:
        inside = np.interp(t, knots_t, knots_a)
        return np.where(
            t < knots_t[0],
            knots_a[0] + (t - knots_t[0]) * rate,
            np.where(t > knots_t[-1], knots_a[-1] + (t - knots_t[-1]) * rate, inside),
        )

    column_azimuth = azimuth_at(column_time)
    cut = column_azimuth[0] if cut_azimuth_deg is None else cut_azimuth_deg
    scan = np.floor((column_azimuth - cut) / 360.0).astype(np.int64)
    scan -= scan[0]
    scan = np.maximum.accumulate(scan)
    n_scans = int(scan[-1]) + 1
    first = np.searchsorted(scan, np.arange(n_scans))
    column = np.arange(len(scan)) - first[scan]
    width = int(column.max()) + 1

    # Per-cell firing-sequence start times; padded cells continue the sequence clock.
    sequence_s = sensor_model.sequence_us * 1e-6
    start = column_time[first]
    cell_time = start[:, None] + np.arange(width)[None, :] * sequence_s
    cell_time[scan, column] = column_time
    valid_cells = np.zeros((n_scans, width), dtype=bool)
    valid_cells[scan, column] = True

    order = np.argsort(-calib.vert, kind="stable")
    laser_time = cell_time[:, None, :] + sensor_model.laser_us[order][None, :, None] * 1e-6
    alpha = np.radians(azimuth_at(laser_time)) - calib.rot[order][None, :, None]
    omega = np.broadcast_to(calib.vert[order][None, :, None], alpha.shape)
    direction = np.stack([np.cos(omega) * np.cos(alpha), -np.cos(omega) * np.sin(alpha), np.sin(omega)], axis=-1)
    vo, ho = calib.vert_offset[order][None, :, None], calib.horiz_offset[order][None, :, None]
    origin = np.stack(
        [
            -vo * np.sin(omega) * np.cos(alpha) + ho * np.sin(alpha),
            vo * np.sin(omega) * np.sin(alpha) + ho * np.cos(alpha),
            np.broadcast_to(vo * np.cos(omega), alpha.shape),
        ],
        axis=-1,
    )

    def grid(values: np.ndarray, fill) -> np.ndarray:
        """(P * columns, lasers) per-firing values -> (S, H, W) in elevation order."""
        out = np.full((n_scans, width, lasers), fill, dtype=values.dtype)
        out[scan, column] = values.reshape(-1, lasers)
        return np.moveaxis(out, 2, 1)[:, order]

    raw = grid(distance, 0)
    valid = np.broadcast_to(valid_cells[:, None, :], raw.shape)
    hit = valid & (raw > 0)
    dist_correction = calib.dist[order][None, :, None]
    ranges = np.where(hit, raw * resolution + dist_correction, np.nan)
    attributes = {
        "laser_id": np.broadcast_to(order.astype(np.uint8)[None, :, None], raw.shape).copy(),
        "intensity": grid(reflectivity, 0),
        "valid": valid.copy(),
    }
    if dual:
        second = grid(other_distance.reshape(shape), 0)
        name = "range_last" if return_mode == "strongest" else "range_strongest"
        second_range = np.where(valid & (second > 0), second * resolution + dist_correction, np.nan)
        attributes[name] = second_range.astype(np.float32)
    sensor = {
        "name": f"velodyne:{sensor_model.name}",
        "source": str(path),
        "calibration": None if calibration is None else str(calibration),
        "return_mode": RETURN_MODES[mode_byte] if not dual else f"dual ({return_mode} in ranges)",
        "product_byte": product,
        "model_source": model_source,
        "distance_resolution_m": resolution,
        "layout": "firing order, rows by elevation",
        "columns_per_scan": np.bincount(scan).tolist(),
        "range_unit": "m",
    }
    return Log(
        poses=np.tile(np.eye(4), (n_scans, 1, 1)),
        directions=direction,
        origins=origin,
        ranges=ranges,
        hit=hit,
        times=laser_time,
        attributes=attributes,
        sensor=sensor,
    )
