"""Velodyne spinning sensors (VLP-16, HDL-32E, VLP-32C, HDL-64E) and the thesis's 32 x 32 HDL-32E packet.

The per-laser angles, offsets and firing times come from :mod:`mi_lidar.core.patterns.vendor`.
"""

from __future__ import annotations

import math

import numpy as np

from mi_lidar.core.errors import PatternError
from mi_lidar.core.patterns.firing import TWO_PI, FiringPattern, positive_float, positive_int, wrap_angle
from mi_lidar.core.patterns.vendor import HDL32E, SPINNING_TABLES, SpinningTable


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
        model: ``"vlp16"``, ``"hdl32e"``, ``"vlp32c"`` or ``"hdl64e"`` (case-insensitive).
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
    period = 60.0 / positive_float(where, "rpm", rpm)
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
        w = positive_int(where, "n_firings", n_firings)
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
    azimuth = wrap_angle(rot + math.pi - TWO_PI * time / period)
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
