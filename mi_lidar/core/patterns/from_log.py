"""Firing patterns of real scans: the exact ray directions, origins and times of a logged sweep.

:func:`pattern_from_log` turns one scan of a :class:`~mi_lidar.core.log.Log` into a
:class:`~mi_lidar.core.patterns.FiringPattern`, so a simulated sensor fires exactly the rays of the
real frame. The readers already give every ray, hit or miss, its direction: from the vendor
metadata for Ouster (beam altitude/azimuth tables, encoder angle) and Velodyne (calibration
table, per-laser firing time), from the CARMEN beam layout, and for point clouds from the points
themselves with misses estimated from their row and column (:mod:`mi_lidar.io.cloud`).
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.log import Log
from mi_lidar.core.patterns.firing import FiringPattern


def pattern_from_log(log: Log, scan: int = 0, name: str | None = None) -> FiringPattern:
    """The firing pattern of one scan.

    Args:
        log: Any log.
        scan: Scan index.
        name: Pattern name; ``"<sensor name>-scan<scan>"`` by default.

    Returns:
        A pattern with ``elevation``/``azimuth`` (H, W) rad from the scan's ray directions,
        ``time`` (H, W) s since the scan's first ray, ``period`` = the sensor's rotation period
        when known (``frequency_hz`` in the metadata), else the time span plus one median firing
        interval, ``origin`` (H, W, 3) m when any ray origin is non-zero, and ``beam_id`` from a
        row-constant ``laser_id`` attribute (Velodyne) when present.
    """
    one = log.scan(scan)
    direction = one.directions[0].astype(np.float64)
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    elevation = np.arcsin(np.clip(direction[..., 2], -1.0, 1.0))
    azimuth = np.arctan2(direction[..., 1], direction[..., 0])
    time = one.times[0] - one.times[0].min()
    steps = np.diff(np.sort(np.unique(time)))
    step = float(np.median(steps)) if len(steps) else 1e-6
    period = max(1.0 / float(one.sensor.get("frequency_hz", np.inf)), float(time.max()) + step)
    assert one.origins is not None  # a Log fills absent origins with zeros
    origin = one.origins[0].astype(np.float64)
    laser = one.attributes.get("laser_id")
    beam_id = None
    if laser is not None and np.all(laser[0] == laser[0][:, :1]):
        beam_id = laser[0][:, 0].astype(np.int64)
    return FiringPattern(
        name=name or f"{one.sensor.get('name', 'log')}-scan{scan}",
        elevation=elevation,
        azimuth=azimuth,
        time=time,
        period=period,
        origin=origin if np.any(origin != 0) else None,
        beam_id=beam_id,
    )
