"""Planar scanners: one beam sweeping the horizontal plane (SICK LMS, Hokuyo, the CARMEN logs)."""

from __future__ import annotations

import numpy as np

from mi_lidar.core.patterns.firing import (
    FiringPattern,
    finite_float,
    float_in,
    positive_float,
    positive_int,
    wrap_angle,
)


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
    n = positive_int(where, "n_bearings", n_bearings)
    fov = float_in(where, "fov_deg", fov_deg, 0.0, 360.0, "a span in (0, 360] degrees")
    period = positive_float(where, "period", period)
    start = -fov / 2.0 if start_deg is None else finite_float(where, "start_deg", start_deg)
    step = fov / n
    offset_deg = step * np.arange(n)
    return FiringPattern(
        name=f"planar-{n}",
        elevation=np.zeros((n, 1)),
        azimuth=wrap_angle(np.radians(start + offset_deg))[:, None],
        time=(offset_deg / 360.0 * period)[:, None],
        period=period,
    )
