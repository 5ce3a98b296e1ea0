"""Does a log come from the scene's sensor? Beam count, field of view and range scale compared.

``compare``, ``diagnose`` and ``calibrate`` score a log's own rays in a scene, so a log from
another sensor still gives numbers, but meaningless ones (a planar 2-D log in a 3-D off-road
scene scores an NLL and an F1 like any other). :func:`check_log_sensor` refuses such a pair with
one message naming both sensors and the fix, unless the caller forces it.

Rules (tolerances wide enough for partial sweeps and for every pattern at any firing count):

* beam count: the log's rows ``H`` equal the pattern's rows;
* vertical field of view: elevation spans agree within ``max(2 deg, 10 %)``;
* horizontal field of view (covered azimuth plus one firing step, so 8 firings of a spinning
  sensor still cover 360 deg): agree within ``max(10 deg, 10 %)``;
* range scale: the log's ranges are in metres and the 99th percentile of its returns is at most
  1.5 times the scene sensor's maximum range (a log in millimetres, or of a much longer-range
  sensor, fails).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import SensorMismatchError
from mi_lidar.core.problem import SURFACE_TOLERANCE

RANGE_SCALE_LIMIT = 1.5  # log p99 range / scene max range beyond which the scales disagree


@dataclass
class SensorSummary:
    """What is compared of a sensor.

    Attributes:
        name: pattern or sensor name.
        beams: rows of the range image.
        vertical_deg: elevation span of the rays, degrees.
        horizontal_deg: azimuth coverage of the rays, degrees (at most 360).
        range_m: log: 99th percentile of the returned ranges; scene: the sensor's maximum range (m).
    """

    name: str
    beams: int
    vertical_deg: float
    horizontal_deg: float
    range_m: float

    def describe(self, range_label: str) -> str:
        return (
            f"{self.name}: {self.beams} beams, field of view {self.vertical_deg:.1f} x {self.horizontal_deg:.0f} deg, "
            f"{range_label} {self.range_m:.1f} m"
        )


def fields_of_view(directions: np.ndarray) -> tuple[float, float]:
    """(vertical, horizontal) fields of view (deg) of unit ray directions ``(..., 3)``.

    The horizontal one is 360 deg minus the largest gap between the sorted azimuths plus the
    second largest (one firing step: a sweep of 8 firings covers 360 deg, a 180-deg planar scan
    180 deg plus one beam step), capped at 360.
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    d = d[np.all(np.isfinite(d), axis=1)]
    if d.size == 0:
        return 0.0, 0.0
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    elevation = np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))
    azimuth = np.unique(np.round(np.degrees(np.arctan2(d[:, 1], d[:, 0])), 6))
    if azimuth.size < 2:
        return float(np.ptp(elevation)), 0.0
    gaps = np.sort(np.diff(np.r_[azimuth, azimuth[0] + 360.0]))
    return float(np.ptp(elevation)), float(min(360.0, 360.0 - gaps[-1] + gaps[-2]))


def log_summary(log) -> SensorSummary:
    """The :class:`SensorSummary` of a :class:`~mi_lidar.core.log.Log` (its first scan's rays, all returns)."""
    vertical, horizontal = fields_of_view(log.directions[0])
    returned = log.ranges[log.hit & np.isfinite(log.ranges)]
    name = log.sensor.get("pattern") or log.sensor.get("name") or "unnamed sensor"
    p99 = float(np.percentile(returned, 99)) if returned.size else 0.0
    return SensorSummary(str(name), log.shape[1], vertical, horizontal, p99)


def pattern_summary(pattern, max_range: float) -> SensorSummary:
    """The :class:`SensorSummary` of a firing pattern seen up to ``max_range`` (m)."""
    vertical, horizontal = fields_of_view(pattern.directions())
    return SensorSummary(pattern.name, pattern.shape[0], vertical, horizontal, float(max_range))


def mismatches(log: SensorSummary, scene: SensorSummary, range_unit: str = "m") -> list[str]:
    """What differs between a log's and a scene's sensor, one phrase each (empty: they match)."""
    found = []
    if log.beams != scene.beams:
        found.append(f"{log.beams} beams vs {scene.beams}")
    if abs(log.vertical_deg - scene.vertical_deg) > max(2.0, 0.1 * max(log.vertical_deg, scene.vertical_deg)):
        found.append(f"vertical field of view {log.vertical_deg:.1f} deg vs {scene.vertical_deg:.1f}")
    if abs(log.horizontal_deg - scene.horizontal_deg) > max(10.0, 0.1 * max(log.horizontal_deg, scene.horizontal_deg)):
        found.append(f"horizontal field of view {log.horizontal_deg:.0f} deg vs {scene.horizontal_deg:.0f}")
    if range_unit != "m":
        found.append(f"ranges in {range_unit!r}, not metres")
    elif log.range_m > RANGE_SCALE_LIMIT * scene.range_m:
        found.append(f"returns up to {log.range_m:.1f} m (99th percentile) vs a maximum range of {scene.range_m:.1f} m")
    return found


def check_log_sensor(log, scene, pattern=None, force: bool = False) -> None:
    """Raise :class:`SensorMismatchError` when ``log`` was not recorded by the scene's sensor.

    Args:
        log: the measured :class:`~mi_lidar.core.log.Log` (its ``source``, when known, starts the message).
        scene: the loaded scene; a scene without a ``lidar`` sensor is not checked (unless
            ``pattern`` is given).
        pattern: the firing pattern to compare with instead of the scene sensor's.
        force: only check, never raise (the caller asked to go on).
    """
    from mi_lidar.scene.loading import scene_lidar_sensor, scene_sensor_model

    sensor = scene_lidar_sensor(scene)
    if force or (sensor is None and pattern is None):
        return
    expected = pattern_summary(pattern or sensor.pattern, scene_sensor_model(scene)[0].max_range)
    measured = log_summary(log)
    found = mismatches(measured, expected, str(log.sensor.get("range_unit", "m")))
    if found:
        named = f"{log.source}: the" if log.source else "the"
        raise SensorMismatchError(
            f"{named} log's sensor ({measured.describe('99 % of returns within')}) does not match the scene's "
            f"`lidar` sensor ({expected.describe('max range')}): {'; '.join(found)}. Use the scene the log was "
            "recorded in, set the scene sensor's pattern to the log's, or pass --force to go on anyway"
        )


def log_scene(log, scene, force: bool = False):
    """The scene to score ``log`` in: ``scene``, loaded when it is an XML path, checked by :func:`check_log_sensor`.

    Raises:
        SensorMismatchError: ``log`` was not recorded by the scene's sensor (unless ``force``).
    """
    from mi_lidar.scene.loading import load_scene

    if not hasattr(scene, "shapes"):
        scene = load_scene(scene)
    check_log_sensor(log, scene, force=force)
    return scene


SURFACE_SHARE_WARNING = 0.25  # below this share of returns on a surface, the scene is probably not the log's


def scene_warnings(near_surface: np.ndarray | None, hit: np.ndarray) -> list[str]:
    """A warning when few of a log's returns lie on the scene's surfaces (an empty list when most do).

    A log in its own scene has most returns within :data:`SURFACE_TOLERANCE` of an element their
    beam reaches (measured: 100 % in the indoor room, 98 % on the street, 86 % off-road among permeable
    ellipsoids); the Intel log in the indoor room has 2.7 %. Below :data:`SURFACE_SHARE_WARNING` the
    scene or the log's poses are probably wrong, and every figure computed on the pair means little.
    It catches gross mismatches only: small pose errors keep many returns near a wall (the room log
    with its poses moved 2 / 5 / 30 m: 37 / 16 / 0 %; the street log moved 2 m along x: 80 %).

    Args:
        near_surface: (N,) from :meth:`~mi_lidar.core.problem.Problem.near_surface` (None: not checked).
        hit: (N,) the log's measured return flags.
    """
    returns = int(np.count_nonzero(hit))
    if near_surface is None or returns == 0:
        return []
    share = np.count_nonzero(near_surface) / returns
    if share >= SURFACE_SHARE_WARNING:
        return []
    return [
        f"only {share:.1%} of {returns:,} measured returns lie within {SURFACE_TOLERANCE:g} m of a scene element "
        "along their beam (most do in the log's own scene): check that the scene is the one the log was recorded "
        "in and that the log's poses are in the scene's frame"
    ]
