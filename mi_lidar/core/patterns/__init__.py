"""Firing patterns: the direction, origin and timestamp of every ray of one Lidar sweep.

A :class:`FiringPattern` lays the rays of one sweep out as an ``H x W`` grid: ``H`` beams
(rows, sorted by elevation, highest first, like a range image) by ``W`` firings (columns, in
firing order). Every array is numpy, angles are radians and times are seconds since the start
of the sweep. Directions are in the ROS sensor frame: x forward, y left, z up; azimuth is
counter-clockwise from +x and elevation positive up, so a ray points along
``(cos el cos az, cos el sin az, sin el)``.

Factories build the patterns of real sensors from vendor tables (:mod:`mi_lidar.core.patterns.vendor`)
and of generic scanners:

=====================  ===========================================================
factory                pattern
=====================  ===========================================================
:func:`planar`         one beam sweeping a plane (SICK, Hokuyo)
:func:`spinning`       Velodyne VLP-16, HDL-32E, HDL-64E
:func:`ouster`         Ouster OS-1 from its metadata JSON, or nominal OS-1-32/64/128
:func:`packet_32x32`   the 32 x 32 Lidar packet of the thesis (HDL-32E)
:func:`raster`         solid-state scanner sweeping row by row
:func:`rosette`        non-repetitive rosette of two counter-rotating prisms (Livox)
:func:`from_table`     a user table (CSV or NPY); :func:`to_table` writes one
=====================  ===========================================================

:func:`get_pattern` finds any of them by name (:data:`PATTERN_NAMES`) or by file path.

Example:
    >>> from mi_lidar.core.patterns import get_pattern
    >>> p = get_pattern("vlp16")
    >>> p.shape, round(p.period, 3)
    ((16, 1808), 0.1)
    >>> p.directions().shape
    (16, 1808, 3)
"""

from __future__ import annotations

import csv
import inspect
import json
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import PatternError
from mi_lidar.core.patterns.vendor import (
    HDL32E,
    OS1_BEAM_ORIGIN_MM,
    OS1_GEN1_ALTITUDE_SPAN_DEG,
    OS1_GEN1_AZIMUTH_CYCLE_DEG,
    OS1_LIDAR_TO_SENSOR,
    SPINNING_TABLES,
    SpinningTable,
)

TWO_PI = 2.0 * math.pi
GOLDEN_FRACTION = (math.sqrt(5.0) - 1.0) / 2.0  # 0.618..., the most irrational step


@dataclass(frozen=True, eq=False)
class FiringPattern:
    """The rays of one Lidar sweep on an ``H x W`` (beams x firings) grid.

    The constructor validates every field and stores read-only float64 copies, so a pattern
    can be shared freely. Patterns compare by identity; compare their arrays to test equality.

    Attributes:
        name: Pattern name, e.g. ``"vlp16"``.
        elevation: (H, W) float64, radians, positive up, within [-pi/2, pi/2].
        azimuth: (H, W) float64, radians, counter-clockwise from +x. Factories wrap it to
            [-pi, pi); any finite value is accepted.
        time: (H, W) float64, seconds since the sweep start, within [0, period).
        period: Sweep duration, s.
        origin: (H, W, 3) float64 beam-origin offsets in the sensor frame, m (Ouster's
            ``lidar_origin_to_beam_origin``, Velodyne HDL-64E offset corrections), or None
            when every beam leaves from the sensor origin.
        beam_id: (H,) int64, the sensor's own laser number of each row, or None for
            ``arange(H)``.
    """

    name: str
    elevation: np.ndarray
    azimuth: np.ndarray
    time: np.ndarray
    period: float
    origin: np.ndarray | None = None
    beam_id: np.ndarray | None = None

    def __post_init__(self):
        where = f"pattern {self.name!r}"
        period = _positive_float(where, "period", self.period)
        elevation = _finite_grid(where, "elevation", self.elevation)
        shape = elevation.shape
        azimuth = _finite_grid(where, "azimuth", self.azimuth, shape)
        time = _finite_grid(where, "time", self.time, shape)
        if np.any(np.abs(elevation) > math.pi / 2 + 1e-12):
            bad = float(elevation.flat[np.argmax(np.abs(elevation))])
            raise PatternError(
                f"{where}: elevation {bad!r} rad is outside [-pi/2, pi/2]; give elevations in radians, positive up"
            )
        if time.min() < 0.0 or time.max() >= period:
            bad = float(time.min() if time.min() < 0.0 else time.max())
            raise PatternError(
                f"{where}: time {bad!r} s is outside [0, period = {period!r} s); "
                "give times since the sweep start, or a longer period"
            )
        origin = self.origin
        if origin is not None:
            origin = np.array(origin, dtype=np.float64)
            if origin.shape != shape + (3,):
                raise PatternError(
                    f"{where}: origin has shape {origin.shape}, expected {shape + (3,)} "
                    "(one 3D offset per ray, m), or pass origin=None"
                )
            if not np.all(np.isfinite(origin)):
                raise PatternError(f"{where}: origin holds non-finite values; give offsets in m")
            origin.setflags(write=False)
        beam_id = self.beam_id
        if beam_id is not None:
            beam_id = np.array(beam_id)
            if beam_id.shape != (shape[0],) or not np.issubdtype(beam_id.dtype, np.integer):
                raise PatternError(
                    f"{where}: beam_id must be {shape[0]} integers (one per row), got "
                    f"dtype {beam_id.dtype} and shape {beam_id.shape}; or pass beam_id=None"
                )
            beam_id = beam_id.astype(np.int64)
            beam_id.setflags(write=False)
        object.__setattr__(self, "period", period)
        object.__setattr__(self, "elevation", elevation)
        object.__setattr__(self, "azimuth", azimuth)
        object.__setattr__(self, "time", time)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "beam_id", beam_id)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W): number of beams (rows) and firings (columns)."""
        return self.elevation.shape

    def directions(self) -> np.ndarray:
        """Unit ray directions in the sensor frame.

        Returns:
            (H, W, 3) float32 array ``(cos el cos az, cos el sin az, sin el)``.
        """
        cos_el = np.cos(self.elevation)
        d = np.stack(
            [cos_el * np.cos(self.azimuth), cos_el * np.sin(self.azimuth), np.sin(self.elevation)],
            axis=-1,
        )
        return d.astype(np.float32)

    def origins(self) -> np.ndarray:
        """Ray origins in the sensor frame, m.

        Returns:
            (H, W, 3) float32 array; zeros when :attr:`origin` is None.
        """
        if self.origin is None:
            return np.zeros(self.shape + (3,), dtype=np.float32)
        return self.origin.astype(np.float32)


# ------------------------------------------------------------------------------------------
# Generic scanners
# ------------------------------------------------------------------------------------------


def planar(
    n_bearings: int = 360,
    fov_deg: float = 360.0,
    period: float = 0.1,
    start_deg: float | None = None,
) -> FiringPattern:
    """A single beam sweeping the horizontal plane counter-clockwise (SICK LMS, Hokuyo).

    Bearing ``i`` is ``start_deg + i * fov_deg / n_bearings``; the default start,
    ``-fov_deg / 2``, centres the fan on +x, which is the CARMEN convention of the Intel
    Research Lab log (180 bearings from -90 to +89 deg). The mirror turns once per period
    at constant speed, so bearing ``i`` fires at ``(bearing_i - start) / 360 deg * period``.

    Args:
        n_bearings: Number of bearings H (> 0).
        fov_deg: Angular span of the fan, degrees, in (0, 360].
        period: Duration of one mirror revolution, s (> 0).
        start_deg: Bearing of the first beam, degrees; None centres the fan on +x.

    Returns:
        An (n_bearings, 1) pattern named ``"planar-<n_bearings>"``: each bearing is one beam (row)
        fired once per scan, as planar logs are read (:func:`mi_lidar.io.carmen.read_carmen`), so
        per-beam effects (bias, angle offsets) are per bearing.

    Raises:
        PatternError: A parameter is out of range.
    """
    where = "planar"
    n = _positive_int(where, "n_bearings", n_bearings)
    fov = _float_in(where, "fov_deg", fov_deg, 0.0, 360.0, "a span in (0, 360] degrees")
    period = _positive_float(where, "period", period)
    start = -fov / 2.0 if start_deg is None else _finite_float(where, "start_deg", start_deg)
    step = fov / n
    offset_deg = step * np.arange(n)
    return FiringPattern(
        name=f"planar-{n}",
        elevation=np.zeros((n, 1)),
        azimuth=_wrap(np.radians(start + offset_deg))[:, None],
        time=(offset_deg / 360.0 * period)[:, None],
        period=period,
    )


def raster(
    h_fov_deg: float = 120.0,
    v_fov_deg: float = 25.0,
    width: int = 240,
    height: int = 64,
    period: float = 0.1,
) -> FiringPattern:
    """A solid-state scanner that sweeps row by row, top to bottom, left to right.

    Rays sit at the centres of a ``height x width`` grid of equal angular cells centred on
    +x; ray ``(r, c)`` fires at ``(r * width + c) * period / (width * height)``.

    Args:
        h_fov_deg: Horizontal field of view, degrees, in (0, 360].
        v_fov_deg: Vertical field of view, degrees, in (0, 180].
        width: Columns W (> 0).
        height: Rows H (> 0).
        period: Frame duration, s (> 0).

    Returns:
        A (height, width) pattern named ``"raster"``.

    Raises:
        PatternError: A parameter is out of range.
    """
    where = "raster"
    h_fov = _float_in(where, "h_fov_deg", h_fov_deg, 0.0, 360.0, "a span in (0, 360] degrees")
    v_fov = _float_in(where, "v_fov_deg", v_fov_deg, 0.0, 180.0, "a span in (0, 180] degrees")
    w = _positive_int(where, "width", width)
    h = _positive_int(where, "height", height)
    period = _positive_float(where, "period", period)
    el_deg = v_fov / 2.0 - (np.arange(h) + 0.5) * v_fov / h
    az_deg = h_fov / 2.0 - (np.arange(w) + 0.5) * h_fov / w
    elevation, azimuth = np.meshgrid(np.radians(el_deg), _wrap(np.radians(az_deg)), indexing="ij")
    time = np.arange(h * w, dtype=np.float64).reshape(h, w) * (period / (h * w))
    return FiringPattern("raster", elevation, azimuth, time, period)


def rosette(
    n_points: int = 20000,
    period: float = 0.1,
    fov_deg: float = 38.4,
    petals: int = 100,
) -> FiringPattern:
    """A non-repetitive rosette like Livox's: two wedge prisms turning in opposite directions.

    Each prism deflects the beam by ``fov_deg / 4``; their deflections add, so the beam's
    angular offset from +x is ``p(t) = fov/4 * (exp(i w1 t) + exp(-i w2 t))``: a rose whose
    lobes reach ``fov / 2`` off axis. The prism frequencies are set so that one sweep traces
    ``petals`` lobes, ``(w1 + w2) / 2 pi = petals / period``, while the rose turns by
    ``(w1 - w2) / 2 * period = pi * (1 + 0.618... / petals)`` rad: a little more than the half
    turn that tiles the disc, so the lobes of the next sweep fall between those of this one.
    The frequency ratio is irrational, so the pattern never repeats and coverage grows with
    integration time. An offset ``(rho, beta)`` in polar form gives the direction
    ``(cos rho, sin rho cos beta, sin rho sin beta)``.

    Args:
        n_points: Rays per sweep W (> 0), fired at a constant rate.
        period: Sweep duration, s (> 0).
        fov_deg: Diameter of the circular field of view, degrees, in (0, 180).
        petals: Lobes per sweep (> 0); more lobes cover the field more evenly.

    Returns:
        A (1, n_points) pattern named ``"rosette"``.

    Raises:
        PatternError: A parameter is out of range.
    """
    where = "rosette"
    n = _positive_int(where, "n_points", n_points)
    period = _positive_float(where, "period", period)
    fov = _float_in(where, "fov_deg", fov_deg, 0.0, 180.0, "a cone in (0, 180) degrees", True)
    n_petals = _positive_int(where, "petals", petals)
    t = np.arange(n, dtype=np.float64) * (period / n)
    f_sum = n_petals / period  # (w1 + w2) / 2 pi, Hz
    f_diff = (1.0 + GOLDEN_FRACTION / n_petals) / period  # (w1 - w2) / 2 pi, Hz
    f1, f2 = (f_sum + f_diff) / 2.0, (f_sum - f_diff) / 2.0  # prism frequencies, Hz
    p = np.radians(fov) / 4.0 * (np.exp(1j * TWO_PI * f1 * t) + np.exp(-1j * TWO_PI * f2 * t))
    rho, beta = np.abs(p), np.angle(p)
    elevation = np.arcsin(np.sin(rho) * np.sin(beta))
    azimuth = np.arctan2(np.sin(rho) * np.cos(beta), np.cos(rho))
    return FiringPattern("rosette", elevation[None, :], azimuth[None, :], t[None, :], period)


# ------------------------------------------------------------------------------------------
# Spinning multi-beam sensors
# ------------------------------------------------------------------------------------------


def spinning(model: str, n_firings: int | None = None, rpm: float = 600.0) -> FiringPattern:
    """A Velodyne spinning Lidar with its real per-laser angles and firing timing.

    The rotor turns clockwise seen from above and the sweep starts pointing backwards
    (-x), so the middle column looks forward and the range image reads left to right like
    a panorama. Laser ``k`` of firing ``n`` fires at ``t = n * dt + tau_k`` (``tau_k`` from
    the vendor's timing table) and points at azimuth ``rot_k + pi - 2 pi t / period``, the
    rotor angle at its own firing time plus its rotational correction. By default
    ``dt`` is the vendor's firing cycle and ``W = floor(period / cycle)`` (1808 firings for
    a VLP-16 at 600 rpm); with ``n_firings`` the firings are spread evenly over the
    revolution (``dt = period / n_firings``) keeping the lasers' offsets within a firing.
    HDL-64E beams leave from offset origins (its calibration's vertical and horizontal
    offset corrections); the other models fire from the sensor origin.

    Args:
        model: ``"vlp16"``, ``"hdl32e"`` or ``"hdl64e"`` (case-insensitive).
        n_firings: Columns W, or None for the vendor's firings per revolution at ``rpm``.
        rpm: Rotor speed, revolutions per minute (> 0); ``period = 60 / rpm``.

    Returns:
        An (L, W) pattern, L lasers sorted by elevation (highest first), ``beam_id`` the
        vendor laser numbers.

    Raises:
        PatternError: Unknown model, non-positive ``rpm`` or ``n_firings``, or firings
            closer together than one firing sequence lasts.
    """
    where = "spinning"
    key = str(model).lower()
    if key not in SPINNING_TABLES:
        raise PatternError(f"{where}: unknown model {model!r}; choose one of {', '.join(SPINNING_TABLES)}")
    table = SPINNING_TABLES[key]
    period = 60.0 / _positive_float(where, "rpm", rpm)
    tau = np.asarray(table.firing_offset_s)
    if n_firings is None:
        w = math.floor(period / table.cycle_s)
        if w < 1:
            raise PatternError(
                f"{where}: rpm {rpm!r} is too fast for the {table.name}: one revolution "
                f"({period:g} s) is shorter than one firing cycle ({table.cycle_s:g} s)"
            )
        dt = table.cycle_s
    else:
        w = _positive_int(where, "n_firings", n_firings)
        dt = period / w
        if tau.max() >= dt:
            raise PatternError(
                f"{where}: n_firings {n_firings!r} puts firings {dt * 1e6:.3f} us apart, but "
                f"one {table.name} firing sequence lasts {tau.max() * 1e6:.3f} us; use at most "
                f"{math.ceil(period / tau.max()) - 1} firings at {rpm!r} rpm"
            )
    order = np.argsort(-np.asarray(table.elevation_deg), kind="stable")
    time = np.arange(w)[None, :] * dt + tau[order][:, None]
    rot = np.radians(np.asarray(table.azimuth_offset_deg)[order])[:, None]
    azimuth = _wrap(rot + math.pi - TWO_PI * time / period)
    elevation_deg = np.asarray(table.elevation_deg)[order]
    elevation = np.broadcast_to(np.radians(elevation_deg)[:, None], (len(order), w))
    return FiringPattern(
        name=table.name,
        elevation=elevation,
        azimuth=azimuth,
        time=time,
        period=period,
        origin=_velodyne_origins(table, order, elevation, azimuth),
        beam_id=order,
    )


def _velodyne_origins(
    table: SpinningTable, order: np.ndarray, elevation: np.ndarray, azimuth: np.ndarray
) -> np.ndarray | None:
    """Beam origins of a Velodyne calibration with offset corrections, or None without.

    The vertical offset ``v`` lies in the beam's vertical plane, perpendicular to the beam,
    and the horizontal offset ``h`` is horizontal and perpendicular to it:
    ``origin = v (-sin el cos az, -sin el sin az, cos el) + h (-sin az, cos az, 0)``, so the
    point at range ``r`` is ``origin + r * direction`` as in Velodyne's point formula.

    Args:
        table: The sensor's table.
        order: (L,) laser numbers of the rows.
        elevation: (L, W) elevations, rad.
        azimuth: (L, W) azimuths, rad.

    Returns:
        (L, W, 3) offsets in m, or None when the table has no offsets.
    """
    if not table.vertical_offset_m:
        return None
    v = np.asarray(table.vertical_offset_m)[order][:, None]
    h = np.asarray(table.horizontal_offset_m)[order][:, None]
    sin_el = np.sin(elevation)
    return np.stack(
        [
            -v * sin_el * np.cos(azimuth) - h * np.sin(azimuth),
            -v * sin_el * np.sin(azimuth) + h * np.cos(azimuth),
            v * np.cos(elevation),
        ],
        axis=-1,
    )


def packet_32x32() -> FiringPattern:
    """The 32 x 32 Lidar packet of the thesis (sec. 4.4): 32 yaw angles x 32 pitch angles.

    The thesis's off-road logs come from a Velodyne HDL-32E; an observation ``z`` is one
    packet of rays fired from a common sensor pose, "32 yaw angles, with 32 pitch angles at
    each yaw angle", and a packet spans "about 1.8 deg" of azimuth. The packet rate of its
    Table 4.5 (210,764 packets in 116.5 s, about 1,808 per second) is the HDL-32E's UDP
    packet rate, so a packet lasts 12 HDL-32E firing cycles, 552.96 us.

    Here the 32 rows are the HDL-32E lasers (highest first) and the 32 yaw columns tile
    [-0.9, +0.9] deg around +x, in firing order (clockwise, so azimuth decreases). All
    pitch angles of a yaw share its timestamp ``k * period / 32``.

    Returns:
        A (32, 32) pattern named ``"packet32"`` with period 552.96 us.
    """
    span_deg = 1.8
    n = 32
    period = 12 * HDL32E.cycle_s
    order = np.argsort(-np.asarray(HDL32E.elevation_deg), kind="stable")
    yaw_deg = span_deg / 2.0 - (np.arange(n) + 0.5) * span_deg / n
    elevation, azimuth = np.meshgrid(
        np.radians(np.asarray(HDL32E.elevation_deg)[order]), np.radians(yaw_deg), indexing="ij"
    )
    time = np.broadcast_to(np.arange(n) * (period / n), (n, n))
    return FiringPattern("packet32", elevation, azimuth, time, period, beam_id=order)


# ------------------------------------------------------------------------------------------
# Ouster
# ------------------------------------------------------------------------------------------


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
        h = 32 if beams is None else _positive_int(where, "beams", beams)
        if h not in (32, 64, 128):
            raise PatternError(
                f"{where}: no nominal table for beams={beams!r}; choose 32, 64 or 128, "
                "or pass the sensor's metadata JSON"
            )
        w = 1024 if columns is None else _positive_int(where, "columns", columns)
        altitude_deg = np.linspace(*OS1_GEN1_ALTITUDE_SPAN_DEG, h)
        azimuth_deg = np.resize(np.asarray(OS1_GEN1_AZIMUTH_CYCLE_DEG), h)
        origin_mm = OS1_BEAM_ORIGIN_MM
        lidar_to_sensor = np.asarray(OS1_LIDAR_TO_SENSOR)
        shifts = None
        hz = 10.0
        name = f"os1-{h}"
    else:
        meta = _read_ouster_metadata(metadata)
        altitude_deg, azimuth_deg = meta["altitude_deg"], meta["azimuth_deg"]
        h, w = len(altitude_deg), meta["columns"]
        if beams is not None and beams != h:
            raise PatternError(
                f"{where}: beams={beams!r} but {metadata} describes {h} beams; leave beams=None to use the metadata"
            )
        if columns is not None and columns != w:
            raise PatternError(
                f"{where}: columns={columns!r} but {metadata} has {w} columns per frame; "
                "leave columns=None to use the metadata"
            )
        origin_mm = meta["origin_mm"]
        lidar_to_sensor = meta["lidar_to_sensor"]
        shifts = meta["shifts"]
        hz = meta["hz"]
        name = meta["name"]
    period = 60.0 / (60.0 * hz if rpm is None else _positive_float(where, "rpm", rpm))
    if shifts is None:
        shifts = np.rint((azimuth_deg - azimuth_deg.min()) * w / 360.0).astype(np.int64)
    order = np.argsort(-altitude_deg, kind="stable")
    column = np.arange(w)[None, :]
    mid = (column - shifts[order][:, None]) % w if destaggered else np.broadcast_to(column, (h, w))

    # --------------------- Vendor geometry in the lidar frame (mm) ---------------------
    enc = TWO_PI * (1.0 - mid / w)  # encoder angle, rad
    heading = enc - np.radians(azimuth_deg[order])[:, None]  # beam azimuth, rad
    alt = np.radians(altitude_deg[order])[:, None]  # beam altitude, rad
    d = np.stack(
        np.broadcast_arrays(np.cos(heading) * np.cos(alt), np.sin(heading) * np.cos(alt), np.sin(alt)), axis=-1
    )
    beam_origin = origin_mm * np.stack([np.cos(enc), np.sin(enc), np.zeros((h, w))], axis=-1)
    ray_origin = beam_origin - origin_mm * d  # where range 0 lies

    # --------------------- Lidar frame -> sensor frame (m) ---------------------
    rotation, translation = lidar_to_sensor[:3, :3], lidar_to_sensor[:3, 3]
    direction = d @ rotation.T
    origin = (ray_origin @ rotation.T + translation) / 1000.0
    return FiringPattern(
        name=name,
        elevation=np.arcsin(np.clip(direction[..., 2], -1.0, 1.0)),
        azimuth=np.arctan2(direction[..., 1], direction[..., 0]),
        time=mid * (period / w),
        period=period,
        origin=origin,
        beam_id=order,
    )


def _read_ouster_metadata(path: str | os.PathLike) -> dict:
    """Read the fields of an Ouster metadata JSON that a firing pattern needs.

    Args:
        path: Metadata file, legacy flat layout or the newer nested one.

    Returns:
        Dict with ``altitude_deg`` and ``azimuth_deg`` ((H,) float64 arrays), ``columns``
        (int), ``shifts`` ((H,) int64 or None), ``origin_mm`` (float, 0 when absent),
        ``lidar_to_sensor`` ((4, 4) float64, translation in mm, identity when absent, as in
        :mod:`mi_lidar.io.ouster`), ``hz`` (float) and ``name`` (str).

    Raises:
        PatternError: The file is missing, not JSON, or lacks or contradicts a field.
    """
    where = f"ouster metadata {os.fspath(path)}"
    try:
        meta = json.loads(Path(path).read_text())
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
    intrinsics = meta.get("beam_intrinsics", meta)
    data_format = meta.get("data_format", meta.get("lidar_data_format", {}))
    config = meta.get("config_params", {})
    lidar_mode = str(meta.get("lidar_mode", config.get("lidar_mode", "")))

    def angles(key: str) -> np.ndarray:
        if key not in intrinsics:
            raise PatternError(f"{where}: missing {key!r}; the file is not Ouster sensor metadata")
        try:
            values = np.asarray(intrinsics[key], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise PatternError(f"{where}: {key!r} must be a list of degrees") from exc
        if values.ndim != 1 or values.size == 0 or not np.all(np.isfinite(values)):
            raise PatternError(f"{where}: {key!r} must be a non-empty list of finite degrees, got {intrinsics[key]!r}")
        return values

    altitude_deg = angles("beam_altitude_angles")
    azimuth_deg = angles("beam_azimuth_angles")
    if altitude_deg.size != azimuth_deg.size:
        raise PatternError(
            f"{where}: {altitude_deg.size} beam_altitude_angles but {azimuth_deg.size} "
            "beam_azimuth_angles; the metadata is corrupt"
        )
    mode = re.fullmatch(r"(\d+)x(\d+)", lidar_mode)
    columns = data_format.get("columns_per_frame", int(mode.group(1)) if mode else None)
    if not isinstance(columns, int) or columns <= 0:
        raise PatternError(
            f"{where}: columns_per_frame is {columns!r} and lidar_mode is {lidar_mode!r}; "
            "the metadata must give the number of columns per frame"
        )
    pixels = data_format.get("pixels_per_column", altitude_deg.size)
    if pixels != altitude_deg.size:
        raise PatternError(
            f"{where}: pixels_per_column is {pixels!r} but {altitude_deg.size} beam angles are "
            "given; the metadata is corrupt"
        )
    shifts = data_format.get("pixel_shift_by_row")
    if shifts is not None:
        shifts = np.asarray(shifts)
        if shifts.shape != altitude_deg.shape or not np.issubdtype(shifts.dtype, np.integer):
            raise PatternError(
                f"{where}: pixel_shift_by_row must hold {altitude_deg.size} integers, got "
                f"{data_format['pixel_shift_by_row']!r}"
            )
        shifts = shifts.astype(np.int64)
    origin_mm = intrinsics.get("lidar_origin_to_beam_origin_mm", 0.0)
    if not isinstance(origin_mm, (int, float)) or not math.isfinite(origin_mm):
        raise PatternError(f"{where}: lidar_origin_to_beam_origin_mm must be a number of mm, got {origin_mm!r}")
    lidar_to_sensor = _rigid_transform(
        where,
        meta.get("lidar_to_sensor_transform", intrinsics.get("lidar_to_sensor_transform", np.eye(4).ravel().tolist())),
    )
    product = str(meta.get("prod_line", meta.get("sensor_info", {}).get("prod_line", "")))
    return {
        "altitude_deg": altitude_deg,
        "azimuth_deg": azimuth_deg,
        "columns": columns,
        "shifts": shifts,
        "origin_mm": float(origin_mm),
        "lidar_to_sensor": lidar_to_sensor,
        "hz": float(mode.group(2)) if mode else 10.0,
        "name": product.lower() or f"ouster-{altitude_deg.size}",
    }


# ------------------------------------------------------------------------------------------
# User tables
# ------------------------------------------------------------------------------------------

_CSV_ANGLES = ("elevation_deg", "azimuth_deg")
_CSV_GRID = ("row", "col")
_DEFAULT_PERIOD = 0.1


def from_table(path: str | os.PathLike, period: float | None = None) -> FiringPattern:
    """Read a user's firing pattern from a CSV or NPY table.

    Formats (angles in degrees, elevation positive up, azimuth counter-clockwise from +x):

    - **CSV** with a header row naming the columns, in any order: ``elevation_deg``,
      ``azimuth_deg`` (required), ``time_s`` (optional, seconds since the sweep start),
      ``row`` and ``col`` (optional, together: 0-based grid position; every cell of the
      ``(max row + 1) x (max col + 1)`` grid must appear exactly once). Without ``row``/``col``
      the rays form one row in file order.
    - **NPY** array of shape ``(N, 2|3)`` (one row of N rays) or ``(H, W, 2|3)`` (a grid);
      the last axis is ``elevation_deg, azimuth_deg[, time_s]``.

    Without times, rays fire evenly spaced in row-major order over ``period``. With times
    and ``period=None``, the period is the last time plus the mean spacing of the times
    (0.1 s if all rays fire at once).

    Args:
        path: ``.csv`` or ``.npy`` file.
        period: Sweep duration, s; None infers it as above (0.1 s without times).

    Returns:
        The pattern, named after the file stem.

    Raises:
        PatternError: The file is missing or malformed, a column is missing or not numeric,
            a grid cell is missing or repeated, an angle is not finite, or a time lies
            outside [0, period).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".csv":
        columns = _read_csv_columns(p)
    elif suffix == ".npy":
        columns = _read_npy_columns(p)
    else:
        raise PatternError(f"from_table: unsupported table {os.fspath(path)!r}; give a .csv or .npy file")
    where = f"table {os.fspath(path)}"
    for key in _CSV_ANGLES:
        bad = np.flatnonzero(~np.isfinite(columns[key]))
        if bad.size:
            raise PatternError(
                f"{where}: {key} of ray {bad[0]} is {columns[key][bad[0]]!r}; every angle must be "
                "a finite number of degrees"
            )
    steep = np.flatnonzero(np.abs(columns["elevation_deg"]) > 90.0)
    if steep.size:
        raise PatternError(
            f"{where}: elevation_deg of ray {steep[0]} is {columns['elevation_deg'][steep[0]]!r}; "
            "elevations lie in [-90, 90] degrees"
        )
    shape, cell = _grid_cells(where, columns)
    n = columns["elevation_deg"].size
    times = columns.get("time_s")
    if period is not None:
        period = _positive_float(where, "period", period)
    if times is None:
        period = _DEFAULT_PERIOD if period is None else period
        times = np.arange(n) * (period / n)
    elif period is None:
        spacing = (times.max() - times.min()) / max(n - 1, 1)
        period = times.max() + spacing if spacing > 0 else _DEFAULT_PERIOD

    def grid(values: np.ndarray) -> np.ndarray:
        out = np.empty(shape[0] * shape[1])
        out[cell] = values
        return out.reshape(shape)

    return FiringPattern(
        name=p.stem,
        elevation=grid(np.radians(columns["elevation_deg"])),
        azimuth=grid(np.radians(columns["azimuth_deg"])),
        time=grid(times),
        period=period,
    )


def to_table(pattern: FiringPattern, path: str | os.PathLike) -> Path:
    """Write a pattern as a table that :func:`from_table` reads back.

    CSV gets the columns ``elevation_deg, azimuth_deg, time_s, row, col`` (17 significant
    digits, so angles survive the round trip); NPY gets an ``(H, W, 3)`` float64 array of
    ``elevation_deg, azimuth_deg, time_s``. Neither stores the period, the beam origins or
    the beam ids: pass ``period=`` to :func:`from_table` to restore the period exactly.

    Args:
        pattern: The pattern to write.
        path: Destination ending in ``.csv`` or ``.npy``.

    Returns:
        The path written.

    Raises:
        PatternError: The suffix is neither ``.csv`` nor ``.npy``.
    """
    p = Path(path)
    stack = np.stack([np.degrees(pattern.elevation), np.degrees(pattern.azimuth), pattern.time], axis=-1)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        np.save(p, stack)
    elif suffix == ".csv":
        h, w = pattern.shape
        rows, cols = np.divmod(np.arange(h * w), w)
        with p.open("w", newline="") as f:
            out = csv.writer(f)
            out.writerow([*_CSV_ANGLES, "time_s", *_CSV_GRID])
            for (el, az, t), r, c in zip(stack.reshape(-1, 3), rows, cols):
                out.writerow([f"{el:.17g}", f"{az:.17g}", f"{t:.17g}", r, c])
    else:
        raise PatternError(f"to_table: unsupported table {os.fspath(path)!r}; use .csv or .npy")
    return p


def _read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    """Columns of a pattern CSV as arrays; see :func:`from_table` for the format."""
    where = f"table {os.fspath(path)}"
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            header = [name.strip() for name in reader.fieldnames or []]
            records = [[(v or "").strip() for v in rec.values()] for rec in reader]
    except OSError as exc:
        raise PatternError(f"cannot read {where} ({exc.strerror}); check the path") from exc
    except (UnicodeDecodeError, csv.Error) as exc:
        raise PatternError(f"{where} is not a text CSV file ({exc})") from exc
    missing = [key for key in _CSV_ANGLES if key not in header]
    if missing:
        raise PatternError(
            f"{where}: missing column(s) {', '.join(missing)} in header {header!r}; the header "
            "must read elevation_deg,azimuth_deg[,time_s][,row,col]"
        )
    if ("row" in header) != ("col" in header):
        raise PatternError(f"{where}: header {header!r} has only one of row/col; give both or none")
    if not records:
        raise PatternError(f"{where} holds a header but no rays; add one line per ray")
    wanted = [key for key in (*_CSV_ANGLES, "time_s", *_CSV_GRID) if key in header]
    columns = {}
    for key in wanted:
        j = header.index(key)
        values = np.empty(len(records))
        for i, rec in enumerate(records):
            try:
                values[i] = float(rec[j])
            except (ValueError, IndexError) as exc:
                text = rec[j] if j < len(rec) else ""
                raise PatternError(
                    f"{where}, line {i + 2}: {key} is {text!r}, not a number; fill every column"
                ) from exc
        columns[key] = values
    return columns


def _read_npy_columns(path: Path) -> dict[str, np.ndarray]:
    """Columns of a pattern NPY as flat arrays in row-major grid order, with the grid shape."""
    where = f"table {os.fspath(path)}"
    try:
        array = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise PatternError(f"cannot read {where} ({exc}); check the path") from exc
    except ValueError as exc:
        raise PatternError(f"{where} is not a plain numeric NPY array ({exc})") from exc
    if array.ndim not in (2, 3) or array.shape[-1] not in (2, 3) or 0 in array.shape:
        raise PatternError(
            f"{where}: array of shape {array.shape}; expected (N, 2|3) or (H, W, 2|3) with "
            "elevation_deg, azimuth_deg[, time_s] on the last axis"
        )
    if not np.issubdtype(array.dtype, np.number):
        raise PatternError(f"{where}: dtype {array.dtype} is not numeric; save float degrees")
    flat = array.reshape(-1, array.shape[-1]).astype(np.float64)
    columns = {"elevation_deg": flat[:, 0], "azimuth_deg": flat[:, 1]}
    if array.shape[-1] == 3:
        columns["time_s"] = flat[:, 2]
    if array.ndim == 3:
        rows, cols = np.divmod(np.arange(flat.shape[0]), array.shape[1])
        columns["row"], columns["col"] = rows.astype(np.float64), cols.astype(np.float64)
    return columns


def _grid_cells(where: str, columns: dict[str, np.ndarray]) -> tuple[tuple[int, int], np.ndarray]:
    """Grid shape and the flat row-major cell of every ray of a table.

    Args:
        where: Context for error messages.
        columns: Table columns; ``row`` and ``col`` optional.

    Returns:
        ``((H, W), cell)`` with ``cell`` an (N,) int array, a permutation of ``arange(H * W)``.

    Raises:
        PatternError: Negative or fractional indices, or a cell missing or repeated.
    """
    n = columns["elevation_deg"].size
    if "row" not in columns:
        return (1, n), np.arange(n)
    index = np.stack([columns["row"], columns["col"]])
    if not np.all(np.isfinite(index)) or np.any(index < 0) or np.any(index != np.round(index)):
        bad = np.flatnonzero(~(np.isfinite(index) & (index >= 0) & (index == np.round(index))))
        ray = int(bad[0] % n)
        raise PatternError(
            f"{where}: ray {ray} has row, col = {index[0, ray]!r}, {index[1, ray]!r}; grid "
            "indices must be integers >= 0"
        )
    rows, cols = index.astype(np.int64)
    shape = (int(rows.max()) + 1, int(cols.max()) + 1)
    cell = rows * shape[1] + cols
    counts = np.bincount(cell, minlength=shape[0] * shape[1])
    if np.any(counts != 1):
        first = int(np.flatnonzero(counts != 1)[0])
        what = "missing" if counts[first] == 0 else f"given {counts[first]} times"
        raise PatternError(
            f"{where}: grid cell row={first // shape[1]}, col={first % shape[1]} of the "
            f"{shape[0]} x {shape[1]} grid is {what}; list every cell exactly once"
        )
    return shape, cell


# ------------------------------------------------------------------------------------------
# Registry
# ------------------------------------------------------------------------------------------

_REGISTRY: dict[str, tuple[Callable[..., FiringPattern], dict]] = {
    "planar-360": (planar, {"n_bearings": 360, "fov_deg": 360.0}),
    "planar-180": (planar, {"n_bearings": 180, "fov_deg": 180.0}),
    "vlp16": (spinning, {"model": "vlp16"}),
    "hdl32e": (spinning, {"model": "hdl32e"}),
    "hdl64e": (spinning, {"model": "hdl64e"}),
    "os1-32": (ouster, {"beams": 32}),
    "os1-64": (ouster, {"beams": 64}),
    "os1-128": (ouster, {"beams": 128}),
    "packet32": (packet_32x32, {}),
    "raster": (raster, {}),
    "rosette": (rosette, {}),
}

PATTERN_NAMES: tuple[str, ...] = tuple(_REGISTRY)
"""Names accepted by :func:`get_pattern`."""


def get_pattern(name_or_path: str | os.PathLike, **kwargs) -> FiringPattern:
    """Build a firing pattern by name or from a file.

    Args:
        name_or_path: One of :data:`PATTERN_NAMES` (case-insensitive), or a path ending in
            ``.csv``/``.npy`` (:func:`from_table`) or ``.json`` (Ouster metadata,
            :func:`ouster`).
        **kwargs: Parameters of the factory, overriding the preset of the name, e.g.
            ``get_pattern("vlp16", rpm=1200)`` or ``get_pattern("planar-180", period=0.2)``.

    Returns:
        The pattern.

    Raises:
        PatternError: Unknown name or parameter, or any error of the factory.
    """
    text = os.fspath(name_or_path)
    suffix = Path(text).suffix.lower()
    if suffix in (".csv", ".npy"):
        factory, preset = from_table, {"path": text}
    elif suffix == ".json":
        factory, preset = ouster, {"metadata": text}
    elif text.lower() in _REGISTRY:
        factory, preset = _REGISTRY[text.lower()]
    else:
        raise PatternError(
            f"unknown firing pattern {text!r}; choose one of {', '.join(PATTERN_NAMES)}, "
            "or give a .csv/.npy table or an Ouster .json metadata file"
        )
    accepted = inspect.signature(factory).parameters
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise PatternError(
            f"pattern {text!r} does not take {', '.join(unknown)}; its parameters are {', '.join(accepted)}"
        )
    return factory(**{**preset, **kwargs})


# ------------------------------------------------------------------------------------------
# Validation helpers
# ------------------------------------------------------------------------------------------


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi), rad."""
    return (np.asarray(angle) + math.pi) % TWO_PI - math.pi


def _finite_grid(where: str, name: str, value, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A read-only float64 copy of a finite, non-empty (H, W) array (of ``shape`` if given)."""
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PatternError(f"{where}: {name} must be a numeric (H, W) array") from exc
    if array.ndim != 2 or 0 in array.shape or (shape is not None and array.shape != shape):
        expected = "(H, W) with H, W >= 1" if shape is None else str(shape)
        raise PatternError(f"{where}: {name} has shape {array.shape}, expected {expected}")
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        i, j = bad[0]
        raise PatternError(
            f"{where}: {name} is {array[i, j]!r} at row {i}, column {j} ({len(bad)} non-finite "
            "values); every value must be finite"
        )
    array.setflags(write=False)
    return array


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


def _finite_float(where: str, name: str, value) -> float:
    """``value`` as a finite float, else PatternError naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise PatternError(f"{where}: {name} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise PatternError(f"{where}: {name} must be finite, got {value!r}")
    return number


def _positive_float(where: str, name: str, value) -> float:
    """``value`` as a finite float > 0, else PatternError naming it."""
    number = _finite_float(where, name, value)
    if number <= 0.0:
        raise PatternError(f"{where}: {name} must be > 0, got {value!r}")
    return number


def _float_in(where: str, name: str, value, low: float, high: float, meaning: str, open_high: bool = False) -> float:
    """``value`` as a float in (low, high] (or (low, high) if ``open_high``)."""
    number = _finite_float(where, name, value)
    if number <= low or number > high or (open_high and number == high):
        raise PatternError(f"{where}: {name} must be {meaning}, got {value!r}")
    return number


def _positive_int(where: str, name: str, value) -> int:
    """``value`` as an int > 0 (bools and fractions refused), else PatternError naming it."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise PatternError(f"{where}: {name} must be a positive integer, got {value!r}")
    return int(value)
