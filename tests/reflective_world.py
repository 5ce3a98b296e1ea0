"""A world of rectangles with known reflectivities, and an independent numpy Lidar simulator for it.

The simulator shares nothing with mi-lidar's core: it intersects rays with the rectangles
analytically in numpy, adds Gaussian range noise, and drops weak returns by its own transcription of
the detector law (logistic in ``ln(rho cos) - 2 ln(r / range50)``), so a test that diagnoses its logs
with mi-lidar checks the model against physics written twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from mi_lidar.core.log import Log
from mi_lidar.core.patterns import get_pattern
from mi_lidar.scene.dicts import MeshElements, scene_dict

WALL_REFLECTIVITIES = (0.04, 0.12, 0.35, 0.9)


@dataclass
class Rectangle:
    """A rectangle: center, two orthogonal unit axes and half sizes (m), reflectivity."""

    center: np.ndarray
    u: np.ndarray
    v: np.ndarray
    half_u: float
    half_v: float
    reflectivity: float

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def corners(self) -> np.ndarray:
        c, a, b = self.center, self.u * self.half_u, self.v * self.half_v
        return np.array([c - a - b, c + a - b, c + a + b, c - a + b])


def rectangles() -> list[Rectangle]:
    """Ground (reflectivity 0.25) and twelve 6 m x 4 m walls at 5-28 m facing the origin, reflectivities cycling."""
    out = [Rectangle(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 60.0, 60.0, 0.25)]
    for i in range(12):
        azimuth = 2 * np.pi * i / 12
        radius = 5.0 + 23.0 * ((i * 5) % 12) / 11
        outward = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        tangent = np.array([-np.sin(azimuth), np.cos(azimuth), 0.0])
        rho = WALL_REFLECTIVITIES[i % len(WALL_REFLECTIVITIES)]
        out.append(Rectangle(radius * outward + np.array([0, 0, 2.0]), tangent, np.array([0, 0, 1.0]), 3.0, 2.0, rho))
    return out


def mitsuba_scene(rects: list[Rectangle]):
    """The same rectangles as a Mitsuba mesh (two triangles each) with per-face reflectivity."""
    vertices = np.concatenate([r.corners() for r in rects])
    faces = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * i for i in range(len(rects))])
    rho = np.repeat([r.reflectivity for r in rects], 2)
    mesh = MeshElements(vertices, faces, p_hit=np.ones(len(faces)), label=np.zeros(len(faces)), reflectivity=rho)
    return mi.load_dict(scene_dict({"world": mesh}))


def poses(n_scans: int, seed: int = 0) -> np.ndarray:
    """Sensor poses 1.2 m above the ground within 2 m of the origin, random headings."""
    rng = np.random.default_rng(seed)
    out = np.repeat(np.eye(4)[None], n_scans, 0)
    heading = rng.uniform(-np.pi, np.pi, n_scans)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = (
        np.cos(heading),
        -np.sin(heading),
        np.sin(heading),
        np.cos(heading),
    )
    out[:, :2, 3] = rng.uniform(-2, 2, (n_scans, 2))
    out[:, 2, 3] = 1.2
    return out


def simulate_numpy(
    rects: list[Rectangle], sensor_poses: np.ndarray, range50: float, width: float, sigma=0.01, seed: int = 0
) -> Log:
    """A VLP-16 log (90 firings per scan) of the rectangles, with weak-return dropout, from numpy alone.

    Args:
        rects: the world.
        sensor_poses: (S, 4, 4) sensor-to-world transforms.
        range50: range (m) at which a white target head-on is kept half of the time.
        width: spread of the detection threshold (nats of returned power).
        sigma: range noise, m.
        seed: random seed.
    """
    pattern = get_pattern("vlp16", n_firings=90)
    local = pattern.directions().astype(np.float64)
    h, w = local.shape[:2]
    rng = np.random.default_rng(seed)
    n_scans = len(sensor_poses)
    ranges = np.full((n_scans, h, w), np.nan, np.float32)
    for s, pose in enumerate(sensor_poses):
        d = local.reshape(-1, 3) @ pose[:3, :3].T
        o = pose[:3, 3]
        best = np.full(len(d), np.inf)
        power = np.zeros(len(d))
        for r in rects:
            n = r.normal
            dn = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((r.center - o) @ n) / dn
            p = o + t[:, None] * d
            inside = (np.abs((p - r.center) @ r.u) <= r.half_u) & (np.abs((p - r.center) @ r.v) <= r.half_v)
            nearer = inside & (t > 1e-6) & (t < best)
            best = np.where(nearer, t, best)
            power = np.where(nearer, r.reflectivity * np.abs(dn), power)
        met = np.isfinite(best)
        margin = (np.log(np.maximum(power, 1e-12)) - 2 * np.log(np.where(met, best, 1.0) / range50)) / width
        kept = met & (rng.uniform(size=len(d)) < 1 / (1 + np.exp(-margin)))
        measured = best + rng.normal(0, sigma, len(d))
        ranges[s] = np.where(kept, measured, np.nan).reshape(h, w)
    times = np.repeat(pattern.time[None], n_scans, 0) + 0.1 * np.arange(n_scans)[:, None, None]
    return Log(
        poses=sensor_poses,
        directions=pattern.directions()[None],
        ranges=ranges,
        hit=np.isfinite(ranges),
        times=times,
        sensor={"pattern": pattern.name},
    )
