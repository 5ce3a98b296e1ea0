"""The true sensor of the synthetic off-road worlds (:mod:`mi_lidar.hybrid.world`): a log of a world.

The **true sensor** (:class:`SensorSpec`) is a 32-beam spinning Lidar with beam divergence. Each
beam is traced as ``1 + n_ring`` sub-rays (centre weight 0.4, ring of ``n_ring`` sub-rays at half
the divergence angle sharing 0.6). Mixed pixels: the sub-ray hits within ``echo_window`` of the
nearest one form the first echo, whose range is the *energy-weighted average* of those sub-ray
ranges (weights = beam weight x reflectance x |cos incidence|); so a beam half on a leaf and half
on the trunk 40 cm behind returns a point in between. The echo is detected with probability
``1 - exp(-E / energy_scale)`` where ``E`` is that energy times ``min(1, (r_ref / r)^2)``; if it is
not detected, the remaining sub-rays form a second echo tried the same way. Detected ranges get
Gaussian noise ``range_noise`` (m); the label and instance are those of the sub-ray contributing
most energy. Rays are cast directly with Mitsuba (``scene.ray_intersect``) on a plain mesh scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.log import Log
from mi_lidar.hybrid.world import World


@dataclass
class SensorSpec:
    """The true sensor: an HDL-32E-like spinning Lidar with beam divergence.

    Attributes:
        n_beams: rows H; elevations evenly spaced in [elev_min, elev_max] (deg).
        n_firings: columns W per 360 deg sweep.
        divergence: full beam divergence, rad.
        n_ring: sub-rays on the ring at half the divergence angle (plus one central sub-ray).
        range_noise: standard deviation of the Gaussian range noise, m.
        min_range, max_range: reported range limits, m.
        echo_window: sub-ray hits within this range of the nearest one form one echo, m.
        energy_scale: echo energy giving detection probability 1 - 1/e.
        r_ref: range below which the received energy saturates, m.
        sweep_time: duration of a sweep, s.
        mount_height: sensor height above the terrain, m.
    """

    n_beams: int = 32
    elev_min: float = -30.67
    elev_max: float = 10.67
    n_firings: int = 512
    divergence: float = 0.004
    n_ring: int = 6
    range_noise: float = 0.02
    min_range: float = 1.0
    max_range: float = 80.0
    echo_window: float = 1.0
    energy_scale: float = 0.05
    r_ref: float = 20.0
    sweep_time: float = 0.1
    mount_height: float = 1.8

    def directions(self) -> np.ndarray:
        """(H, W, 3) float32 central unit ray directions in the sensor frame (x forward, z up)."""
        elev = np.deg2rad(np.linspace(self.elev_max, self.elev_min, self.n_beams))
        az = 2 * np.pi * np.arange(self.n_firings) / self.n_firings
        e, a = np.meshgrid(elev, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).astype(np.float32)

    def sub_rays(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-ray directions (..., 1 + n_ring, 3) around unit directions ``d`` (..., 3) and weights."""
        helper = np.where(np.abs(d[..., 2:3]) < 0.9, [0, 0, 1.0], [1.0, 0, 0])
        e1 = np.cross(d, helper)
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(d, e1)
        ang = 2 * np.pi * np.arange(self.n_ring) / self.n_ring
        ang = ang.reshape((-1,) + (1,) * d.ndim)
        ring = d[None] + np.tan(self.divergence / 4) * (np.cos(ang) * e1[None] + np.sin(ang) * e2[None])
        subs = np.concatenate([d[None], ring])
        subs /= np.linalg.norm(subs, axis=-1, keepdims=True)
        weights = np.array([0.4] + [0.6 / self.n_ring] * self.n_ring)
        return np.moveaxis(subs, 0, -2), weights


def path_poses(world: World, spacing: float = 1.5, sensor: SensorSpec | None = None, margin: float = 8.0) -> np.ndarray:
    """(S, 4, 4) sensor-to-world poses every ``spacing`` m (in x) along the world's vehicle path.

    The sensor sits ``mount_height`` above the terrain, yawed along the path tangent.

    Raises:
        ParameterError: ``spacing`` leaves no scan on the path.
    """
    sensor = sensor or SensorSpec()
    xs = np.arange(margin, world.spec.length - margin, spacing)
    if xs.size == 0 or not spacing > 0:
        raise ParameterError(
            f"spacing={spacing} m leaves no scan on the {world.spec.length:g} m world's path (x = {margin:g} to "
            f"{world.spec.length - margin:g} m); choose a spacing below {max(world.spec.length - 2 * margin, 0):g} m "
            "or a longer world"
        )
    ys = world.path_y(xs)
    dy = (world.path_y(xs + 0.1) - world.path_y(xs - 0.1)) / 0.2
    yaw = np.arctan2(dy, 1.0)
    poses = np.tile(np.eye(4), (len(xs), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :3, 3] = np.stack([xs, ys, world.height(xs, ys) + sensor.mount_height], 1)
    return poses


def _echo(r, energy, active, window):
    """Energy-weighted mean range, energy and mask of the first echo among ``active`` sub-rays."""
    rr = np.where(active, r, np.inf)
    r_min = rr.min(axis=1, keepdims=True)
    member = active & (rr <= r_min + window)
    e = np.where(member, energy, 0.0)
    total = e.sum(axis=1)
    mean = np.where(total > 0, (e * np.where(member, r, 0)).sum(axis=1) / np.maximum(total, 1e-12), np.nan)
    return mean, total, member


def render_log(
    world: World, poses: np.ndarray, sensor: SensorSpec | None = None, seed: int = 0, scans_per_batch: int = 8
) -> Log:
    """Ray-cast the true sensor in ``world`` at ``poses`` and return a labeled :class:`Log`.

    Args:
        world: the synthetic world.
        poses: (S, 4, 4) sensor-to-world transforms.
        sensor: the true sensor (defaults to :class:`SensorSpec`).
        seed: seed of detection and range noise.
        scans_per_batch: scans traced per Mitsuba call (memory vs. call overhead).

    Returns:
        A log with attributes ``label`` and ``instance`` (int32; 0 / -1 for misses).
    """
    from mi_lidar.hybrid.trace import intersect

    sensor = sensor or SensorSpec()
    rng = np.random.default_rng(seed)
    dirs = sensor.directions()
    subs, weights = sensor.sub_rays(dirs)  # (H, W, K, 3)
    h, w, k = subs.shape[:3]
    normals = world.normals
    s_count = len(poses)
    ranges = np.full((s_count, h, w), np.nan, np.float32)
    labels = np.zeros((s_count, h, w), np.int32)
    instances = np.full((s_count, h, w), -1, np.int32)
    scene = world.mitsuba_scene()
    for s0 in range(0, s_count, scans_per_batch):
        batch = poses[s0 : s0 + scans_per_batch]
        b = len(batch)
        d_world = np.einsum("bij,hwkj->bhwki", batch[:, :3, :3], subs).reshape(-1, 3)
        o_world = np.broadcast_to(batch[:, None, None, None, :3, 3], (b, h, w, k, 3)).reshape(-1, 3)
        t, prim = intersect(scene, o_world, d_world)
        t = t.reshape(-1, k)
        prim = prim.reshape(-1, k)
        valid = np.isfinite(t) & (t <= sensor.max_range)
        safe = np.where(valid, prim, 0)
        cos = np.abs(np.sum(normals[safe] * d_world.reshape(-1, k, 3), axis=-1))
        energy = weights * world.reflectance[safe] * cos * valid
        falloff = lambda r: np.minimum(1.0, (sensor.r_ref / np.maximum(r, 1e-3)) ** 2)
        r1, e1, m1 = _echo(t, energy, valid, sensor.echo_window)
        det1 = rng.uniform(size=len(r1)) < 1 - np.exp(-e1 * falloff(np.nan_to_num(r1, nan=1e9)) / sensor.energy_scale)
        r2, e2, m2 = _echo(t, energy, valid & ~m1, sensor.echo_window)
        det2 = rng.uniform(size=len(r2)) < 1 - np.exp(-e2 * falloff(np.nan_to_num(r2, nan=1e9)) / sensor.energy_scale)
        use2 = ~det1 & det2
        r = np.where(det1, r1, np.where(use2, r2, np.nan))
        member = np.where(use2[:, None], m2, m1)
        best = np.argmax(np.where(member, energy, -1), axis=1)
        face = safe[np.arange(len(best)), best]
        r = r + rng.normal(0, sensor.range_noise, len(r))
        ok = np.isfinite(r) & (r >= sensor.min_range) & (r <= sensor.max_range)
        ranges[s0 : s0 + b] = np.where(ok, r, np.nan).reshape(b, h, w)
        labels[s0 : s0 + b] = np.where(ok, world.label[face], 0).reshape(b, h, w)
        instances[s0 : s0 + b] = np.where(ok, world.instance[face], -1).reshape(b, h, w)
    hit = np.isfinite(ranges)
    col_time = np.arange(w) / w * sensor.sweep_time
    times = (np.arange(s_count)[:, None, None] * sensor.sweep_time + col_time[None, None, :]) * np.ones((1, h, 1))
    meta = {
        "name": "synthetic-true-sensor",
        "world_seed": world.seed,
        "min_range": sensor.min_range,
        "max_range": sensor.max_range,
        "divergence": sensor.divergence,
        "range_noise": sensor.range_noise,
    }
    return Log(
        poses=poses,
        directions=dirs[None],
        ranges=ranges,
        hit=hit,
        times=times,
        attributes={"label": labels, "instance": instances},
        sensor=meta,
    )
