"""The firing-pattern type and the argument checks every pattern factory shares.

A :class:`FiringPattern` lays the rays of one sweep out as an ``H x W`` grid: ``H`` beams
(rows, sorted by elevation, highest first, like a range image) by ``W`` firings (columns, in
firing order). Every array is numpy, angles are radians and times are seconds since the start
of the sweep. Directions are in the ROS sensor frame: x forward, y left, z up; azimuth is
counter-clockwise from +x and elevation positive up, so a ray points along
``(cos el cos az, cos el sin az, sin el)``.

The checks (:func:`positive_int`, :func:`float_in`, ...) turn a factory argument into a number or
raise :class:`~mi_lidar.core.errors.PatternError` naming the factory, the argument and the value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import PatternError

TWO_PI = 2.0 * math.pi


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
        period = positive_float(where, "period", self.period)
        elevation = finite_grid(where, "elevation", self.elevation)
        shape = elevation.shape
        azimuth = finite_grid(where, "azimuth", self.azimuth, shape)
        time = finite_grid(where, "time", self.time, shape)
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


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi), rad."""
    return (np.asarray(angle) + math.pi) % TWO_PI - math.pi


def finite_grid(where: str, name: str, value, shape: tuple[int, int] | None = None) -> np.ndarray:
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


def finite_float(where: str, name: str, value) -> float:
    """``value`` as a finite float, else PatternError naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise PatternError(f"{where}: {name} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise PatternError(f"{where}: {name} must be finite, got {value!r}")
    return number


def positive_float(where: str, name: str, value) -> float:
    """``value`` as a finite float > 0, else PatternError naming it."""
    number = finite_float(where, name, value)
    if number <= 0.0:
        raise PatternError(f"{where}: {name} must be > 0, got {value!r}")
    return number


def float_in(where: str, name: str, value, low: float, high: float, meaning: str, open_high: bool = False) -> float:
    """``value`` as a float in (low, high] (or (low, high) if ``open_high``)."""
    number = finite_float(where, name, value)
    if number <= low or number > high or (open_high and number == high):
        raise PatternError(f"{where}: {name} must be {meaning}, got {value!r}")
    return number


def positive_int(where: str, name: str, value) -> int:
    """``value`` as an int > 0 (bools and fractions refused), else PatternError naming it."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise PatternError(f"{where}: {name} must be a positive integer, got {value!r}")
    return int(value)
