"""Solid-state scanners: a row-by-row raster and a Livox-like non-repetitive rosette."""

from __future__ import annotations

import math

import numpy as np

from mi_lidar.core.patterns.firing import TWO_PI, FiringPattern, float_in, positive_float, positive_int, wrap_angle

GOLDEN_FRACTION = (math.sqrt(5.0) - 1.0) / 2.0  # 0.618..., the most irrational step


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
    h_fov = float_in(where, "h_fov_deg", h_fov_deg, 0.0, 360.0, "a span in (0, 360] degrees")
    v_fov = float_in(where, "v_fov_deg", v_fov_deg, 0.0, 180.0, "a span in (0, 180] degrees")
    w = positive_int(where, "width", width)
    h = positive_int(where, "height", height)
    period = positive_float(where, "period", period)
    el_deg = v_fov / 2.0 - (np.arange(h) + 0.5) * v_fov / h
    az_deg = h_fov / 2.0 - (np.arange(w) + 0.5) * h_fov / w
    elevation, azimuth = np.meshgrid(np.radians(el_deg), wrap_angle(np.radians(az_deg)), indexing="ij")
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
    n = positive_int(where, "n_points", n_points)
    period = positive_float(where, "period", period)
    fov = float_in(where, "fov_deg", fov_deg, 0.0, 180.0, "a cone in (0, 180) degrees", True)
    n_petals = positive_int(where, "petals", petals)
    t = np.arange(n, dtype=np.float64) * (period / n)
    f_sum = n_petals / period  # (w1 + w2) / 2 pi, Hz
    f_diff = (1.0 + GOLDEN_FRACTION / n_petals) / period  # (w1 - w2) / 2 pi, Hz
    f1, f2 = (f_sum + f_diff) / 2.0, (f_sum - f_diff) / 2.0  # prism frequencies, Hz
    p = np.radians(fov) / 4.0 * (np.exp(1j * TWO_PI * f1 * t) + np.exp(-1j * TWO_PI * f2 * t))
    rho, beta = np.abs(p), np.angle(p)
    elevation = np.arcsin(np.sin(rho) * np.sin(beta))
    azimuth = np.arctan2(np.sin(rho) * np.cos(beta), np.cos(rho))
    return FiringPattern("rosette", elevation[None, :], azimuth[None, :], t[None, :], period)
