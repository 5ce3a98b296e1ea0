"""An independent numpy room for planar hidden-effect tests: line segments, an N-beam x 1-firing scanner.

The room (12 m x 8 m walls, label 1; a 1 m pillar, label 2; a slanted partition, label 3) is a set of
vertical wall segments, ray cast here in 2D (:func:`tests.planar.world.cast`) and written as a
Mitsuba scene of 2 m high rectangles for the project to load (:func:`scene_xml`). The scanner sits
0.5 m above the floor with ``beams`` bearings over 360 degrees, one firing per scan (planar logs are N
beams x 1 firing); it reports the first wall's distance with Gaussian noise (sigma 1 cm) or nothing
beyond 30 m.

:class:`Hidden` lists the effects the simulator can hide, each written from its physical description:
range scale, per-beam bias, range-proportional noise and a dropout that stops the beam, logistic in
the incidence angle.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tests.planar.world import cast

# x0, y0, x1, y1, label
SEGMENTS = np.array(
    [
        [0, 0, 12, 0, 1],
        [12, 0, 12, 8, 1],
        [12, 8, 0, 8, 1],
        [0, 8, 0, 0, 1],
        [5.5, 3.5, 6.5, 3.5, 2],
        [6.5, 3.5, 6.5, 4.5, 2],
        [6.5, 4.5, 5.5, 4.5, 2],
        [5.5, 4.5, 5.5, 3.5, 2],
        [8.5, 6.8, 10.5, 5.8, 3],
    ],
    float,
)
SIGMA = 0.01  # m
MAX_RANGE = 30.0  # m
HEIGHT = 0.5  # m: scanner above the floor
WALL_HEIGHT = 2.0  # m
PERIOD = 0.1  # s: one mirror turn


def pattern_table(path, beams: int, bearing: np.ndarray | None = None) -> str:
    """Write the firing table of a ``beams``-bearing scanner (one firing per scan; ``bearing`` (rad), default every
    ``360 / beams`` degrees over the full circle); return its path."""
    azimuth = [360.0 * i / beams for i in range(beams)] if bearing is None else np.degrees(bearing)
    rows = [f"{i},0,0.0,{azimuth[i]:.9f},{PERIOD * i / beams:.9f}" for i in range(beams)]
    Path(path).write_text("row,col,elevation_deg,azimuth_deg,time_s\n" + "\n".join(rows) + "\n")
    return str(path)


def scene_xml(
    pattern: str = "planar-360", max_range: float = MAX_RANGE, segments: np.ndarray = SEGMENTS, sigma: float = SIGMA
) -> str:
    """The room (or other ``segments``, rows ``x0, y0, x1, y1, label``) as a Mitsuba scene of vertical rectangles.

    ``pattern`` names the scanner's firing pattern (a registered name or a table, :func:`pattern_table`);
    ``max_range`` (m) is the sensor's maximum range, ``sigma`` (m) its range noise.
    """
    shapes = []
    for i, (x0, y0, x1, y1, label) in enumerate(segments):
        length, angle = np.hypot(x1 - x0, y1 - y0), np.degrees(np.arctan2(y1 - y0, x1 - x0))
        shapes.append(
            f'<shape type="rectangle" id="wall_{i}"><transform name="to_world">'
            f'<scale x="{length / 2}" y="{WALL_HEIGHT / 2}"/><rotate x="1" angle="90"/>'
            f'<rotate z="1" angle="{angle}"/>'
            f'<translate x="{(x0 + x1) / 2}" y="{(y0 + y1) / 2}" z="{WALL_HEIGHT / 2}"/></transform>'
            f'<bsdf type="lidar_material"><integer name="label" value="{int(label)}"/></bsdf></shape>'
        )
    return (
        '<scene version="3.0.0"><integrator type="lidar_integrator"><integer name="max_segments" value="4"/>'
        f'</integrator><sensor type="lidar"><string name="pattern" value="{pattern}"/>'
        f'<float name="max_range" value="{max_range}"/><float name="range_sigma" value="{sigma}"/></sensor>'
        + "".join(shapes)
        + "</scene>"
    )


@dataclass
class Hidden:
    """Effects hidden in a room log (every default is 'absent').

    Attributes:
        scale: range scale (reported = scale x true range).
        bias: (beams,) per-beam range bias, m.
        noise_k: range-proportional noise, m per m (added in quadrature to the 1 cm).
        logistic: (angle50, width), deg: a beam is lost (no return, nothing behind it seen) with
            probability 1 / (1 + exp(-(delta - angle50) / width)), delta the incidence angle.
    """

    scale: float = 1.0
    bias: np.ndarray | None = None
    noise_k: float = 0.0
    logistic: tuple | None = None


def ellipse_path(cx: float = 6.0, cy: float = 4.0, ax: float = 4.0, ay: float = 2.6):
    """A drive around an ellipse (centre and half axes, m), the heading wobbling: ``path(scans) -> (x, y, heading)``."""

    def path(scans: int):
        a = np.linspace(0, 2 * np.pi, scans, endpoint=False)
        return cx + ax * np.cos(a), cy + ay * np.sin(a), a + 0.3 * np.sin(3 * a)

    return path


def room_log(
    hidden: Hidden,
    scans: int = 60,
    beams: int = 360,
    seed: int = 0,
    max_range: float = MAX_RANGE,
    segments: np.ndarray = SEGMENTS,
    path=None,
    bearing: np.ndarray | None = None,
    sigma: float = SIGMA,
) -> dict:
    """Simulate ``scans`` scans with the ``hidden`` effects; the scanner reports nothing beyond ``max_range`` (m).

    ``segments`` are the walls (rows ``x0, y0, x1, y1, label``; label 0 returns nothing), ``path(scans)`` the
    poses (default :func:`ellipse_path`), ``bearing`` (rad) the scanner's beams (default ``beams`` over the full
    circle) and ``sigma`` (m) its range noise.

    Returns:
        The arrays of a ``mi_lidar`` log: ``poses`` (S, 4, 4), ``directions`` (1, beams, 1, 3),
        ``ranges`` (S, beams, 1, NaN = miss), ``hit`` and ``times`` (S, beams, 1).
    """
    rng = np.random.default_rng(seed)
    bearing = 2 * np.pi * np.arange(beams) / beams if bearing is None else np.asarray(bearing, float)
    beams = bearing.size
    walls, labels = segments[:, :4], segments[:, 4]
    along = walls[:, 2:] - walls[:, :2]
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    xs, ys, headings = (path or ellipse_path())(scans)
    poses, ranges, times = [], [], []
    for s, (x, y, heading) in enumerate(zip(xs, ys, headings)):
        pose = np.eye(4)
        pose[:2, :2] = [[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]]
        pose[:3, 3] = (x, y, HEIGHT)
        poses.append(pose)
        direction = np.stack([np.cos(heading + bearing), np.sin(heading + bearing)], axis=1)
        t = cast(np.repeat([[x, y]], beams, 0), direction, walls)  # (beams, segments)
        first = np.argmin(t, axis=1)
        r = t[np.arange(beams), first]
        cos_inc = np.abs(direction[:, 0] * along[first, 1] - direction[:, 1] * along[first, 0])
        keep = np.isfinite(r) & (r <= max_range) & (labels[first] > 0)
        if hidden.logistic is not None:
            angle50, width = hidden.logistic
            delta = np.degrees(np.arccos(np.clip(cos_inc, 0.0, 1.0)))
            keep &= rng.random(beams) >= 1.0 / (1.0 + np.exp(-(delta - angle50) / width))
        bias = 0.0 if hidden.bias is None else np.asarray(hidden.bias)
        spread = np.sqrt(sigma**2 + (hidden.noise_k * np.where(keep, r, 0.0)) ** 2)
        z = hidden.scale * np.where(keep, r, 0.0) + bias + rng.normal(0.0, 1.0, beams) * spread
        hit = keep & (z > 0) & (z <= max_range)
        ranges.append(np.where(hit, z, np.nan)[:, None])
        times.append((s * 0.2 + PERIOD * np.arange(beams) / beams)[:, None])
    directions = np.stack([np.cos(bearing), np.sin(bearing), np.zeros(beams)], axis=1)[:, None]
    stacked = np.stack(ranges).astype(np.float32)
    return {
        "poses": np.stack(poses),
        "directions": directions[None].astype(np.float32),
        "ranges": stacked,
        "hit": np.isfinite(stacked),
        "times": np.stack(times),
    }
