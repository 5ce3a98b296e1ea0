"""An independent numpy street for 3D hidden-effect tests: boxes, poles, a 16-beam spinning Lidar.

The street (labels: 1 ground, 2 buildings, 3 poles, 4 cars) is ray cast here analytically (slabs
for boxes, a quadratic for poles, a plane for the ground) and written as a Mitsuba scene XML for
the project to load (:func:`scene_xml`). The scanner has 16 beams from -15 to +15 deg elevation
and ``columns`` firings per 0.1 s sweep; sweeps are contiguous in time while the car drives along
the street at 10 m/s (log poses are the sweep starts). The sensor reports a Gaussian range (sigma
1 cm, the scene's default) on the first surface, or nothing beyond 100 m.

:class:`Hidden` lists the effects the simulator can hide in a log, each written from its physical
description (not from the project's code): range scale and per-beam bias, range-proportional noise,
dropouts that stop the beam (logistic in incidence, per label, growing with range, random, and weak
returns below the detector's threshold), beam elevation offsets, a mounting error, motion during
the sweep, mixed pixels at depth edges (a share of in-between returns, pure foreground or
background returns otherwise), multiple echoes of a diverging beam (the first or the last one
reported), near clutter, quantization, and two effects outside the catalog: a range bias that
drifts with time, and a range walk (late returns: an exponential delay behind every surface, which
no catalog effect's law has).
Surfaces have a Lambertian reflectivity per label (:data:`REFLECTIVITY`, written into the scene).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# (xmin, xmax, ymin, ymax, zmin, zmax, label)
BOXES = np.array(
    [
        [-20, -4, 9, 19, 0, 12, 2],
        [2, 16, 9, 19, 0, 18, 2],
        [-16, 8, -19, -9, 0, 10, 2],
        [12, 24, -19, -9, 0, 24, 2],
        [4.8, 9.2, 2.6, 4.4, 0, 1.5, 4],
        [-9.0, -4.6, -4.4, -2.6, 0, 1.5, 4],
        [14.0, 18.4, 2.6, 4.4, 0, 1.5, 4],
    ],
    float,
)
POLES = np.array([[-8, -6], [8, -6], [0, 6], [16, -6], [-14, 6]], float)  # x, y
POLE_RADIUS, POLE_HEIGHT, POLE_LABEL = 0.15, 6.0, 3
GROUND_HALF = (60.0, 30.0)  # m: the ground rectangle's half sizes
GROUND_LABEL = 1
REFLECTIVITY = {1: 0.2, 2: 0.6, 3: 0.35, 4: 0.08}  # asphalt, facades, poles, dark car paint
SIGMA = 0.01  # m: the scene's range noise
MAX_RANGE = 100.0
HEIGHT = 1.8  # m: sensor above the ground
PERIOD = 0.1  # s: one sweep
SPEED = 10.0  # m/s along x
ELEVATIONS = np.radians(np.linspace(-15.0, 15.0, 16))
MIXED_OFFSETS = ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))  # (elevation, azimuth) x divergence
MIXED_WEIGHTS = (0.4, 0.15, 0.15, 0.15, 0.15)


def material(label: int) -> str:
    """The ``lidar_material`` of a surface of class ``label`` (its label and reflectivity)."""
    return (
        f'<bsdf type="lidar_material"><integer name="label" value="{label}"/>'
        f'<float name="reflectivity" value="{REFLECTIVITY[label]}"/></bsdf>'
    )


def scene_xml() -> str:
    """The street as a Mitsuba scene (the project's loader reads it)."""
    shapes = []
    for i, (x0, x1, y0, y1, z0, z1, label) in enumerate(BOXES):
        shapes.append(
            f'<shape type="cube" id="box_{i}"><transform name="to_world">'
            f'<scale x="{(x1 - x0) / 2}" y="{(y1 - y0) / 2}" z="{(z1 - z0) / 2}"/>'
            f'<translate x="{(x1 + x0) / 2}" y="{(y1 + y0) / 2}" z="{(z1 + z0) / 2}"/></transform>'
            f"{material(int(label))}</shape>"
        )
    for i, (x, y) in enumerate(POLES):
        shapes.append(
            f'<shape type="cylinder" id="pole_{i}"><point name="p0" x="{x}" y="{y}" z="0"/>'
            f'<point name="p1" x="{x}" y="{y}" z="{POLE_HEIGHT}"/><float name="radius" value="{POLE_RADIUS}"/>'
            f"{material(POLE_LABEL)}</shape>"
        )
    shapes.append(
        f'<shape type="rectangle" id="ground"><transform name="to_world">'
        f'<scale x="{GROUND_HALF[0]}" y="{GROUND_HALF[1]}"/></transform>'
        f"{material(GROUND_LABEL)}</shape>"
    )
    return (
        '<scene version="3.0.0"><integrator type="lidar_integrator"><integer name="max_segments" value="4"/>'
        f'</integrator><sensor type="lidar"><string name="pattern" value="vlp16"/>'
        f'<float name="max_range" value="{MAX_RANGE}"/><float name="range_sigma" value="{SIGMA}"/></sensor>'
        + "".join(shapes)
        + "</scene>"
    )


def cast(origin: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First surface along (N, 3) rays: distance (m, inf where none), unit normal (N, 3) and label (N,)."""
    n = len(origin)
    best = np.full(n, np.inf)
    normal = np.zeros((n, 3))
    label = np.zeros(n, np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for x0, x1, y0, y1, z0, z1, lab in BOXES:
            lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
            t1, t2 = (lo - origin) / direction, (hi - origin) / direction
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            axis = np.argmax(near, axis=1)
            t_in, t_out = near.max(axis=1), far.min(axis=1)
            ok = (t_in <= t_out) & (t_in > 1e-6) & (t_in < best)
            face = np.zeros((n, 3))
            face[np.arange(n), axis] = -np.sign(direction[np.arange(n), axis])
            best, label = np.where(ok, t_in, best), np.where(ok, lab, label)
            normal = np.where(ok[:, None], face, normal)
        for x, y in POLES:
            ox, oy = origin[:, 0] - x, origin[:, 1] - y
            a = direction[:, 0] ** 2 + direction[:, 1] ** 2
            b = 2 * (ox * direction[:, 0] + oy * direction[:, 1])
            c = ox**2 + oy**2 - POLE_RADIUS**2
            disc = b * b - 4 * a * c
            root = np.sqrt(np.maximum(disc, 0.0))
            for t in ((-b - root) / (2 * a), (-b + root) / (2 * a)):
                z = origin[:, 2] + t * direction[:, 2]
                ok = (disc > 0) & (t > 1e-6) & (z >= 0) & (z <= POLE_HEIGHT) & (t < best)
                radial = np.stack([ox + t * direction[:, 0], oy + t * direction[:, 1], np.zeros(n)], axis=1)
                radial /= POLE_RADIUS
                best = np.where(ok, t, best)
                normal = np.where(ok[:, None], radial, normal)
                label = np.where(ok, POLE_LABEL, label)
        t = -origin[:, 2] / direction[:, 2]
        px, py = origin[:, 0] + t * direction[:, 0], origin[:, 1] + t * direction[:, 1]
        ok = (t > 1e-6) & (np.abs(px) <= GROUND_HALF[0]) & (np.abs(py) <= GROUND_HALF[1]) & (t < best)
        best = np.where(ok, t, best)
        normal = np.where(ok[:, None], np.array([0.0, 0.0, 1.0]), normal)
        label = np.where(ok, GROUND_LABEL, label)
    best = np.where(best <= MAX_RANGE, best, np.inf)
    return best, normal, label


def rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation matrix of the rotation vector (rx, ry, rz) (rad), by Rodrigues' formula."""
    w = np.array([rx, ry, rz], float)
    angle = np.linalg.norm(w)
    if angle == 0:
        return np.eye(3)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / angle
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@dataclass
class Hidden:
    """Effects hidden in a street log (every default is 'absent').

    Attributes:
        scale: range scale (reported = scale x true range).
        bias: (16,) per-beam range bias, m.
        noise_k: range-proportional noise, m per m (added in quadrature to the 1 cm).
        logistic: (angle50, width), deg: beams lost with probability 1 / (1 + exp(-(delta - angle50) / width)).
        label_drop: {label: probability} of losing a beam on that label.
        range_dropout: (rate, power): kept with probability exp(-rate (r / 10)^power).
        random_drop: probability of losing any beam.
        elevation: (16,) per-beam elevation offsets, rad.
        mount: (rx, ry, rz, tx, ty, tz): true sensor pose = log pose x this (rad, m, sensor frame).
        velocity: (vx, vy, vz) extra sensor velocity during each sweep (m/s, sensor frame) that the
            log's poses (sweep starts) do not show.
        mixed: (divergence rad, share): 5 sub-rays; at every beam a share of returns report the
            energy-weighted mean of the sub-rays' ranges, the rest one sub-ray's range (chosen by energy).
        echo: (divergence rad, ``first`` or ``last``): 5 sub-rays, each an echo at its surface; the
            sensor reports the nearest or the farthest echo, with one range-noise draw.
        weak: (range50 m, width): the detector keeps a return of power ``rho cos(delta) / r^2`` with
            the logistic probability of ``ln(power)`` against ``ln(1 / range50^2)``, spread ``width``.
        near: (p, scale): near clutter returns with probability p at a half-normal range of that scale, m.
        step: quantization step of reported ranges, m.
        drift: range bias growing with time, m/s (outside the catalog).
        walk: mean of an exponential delay added to every return, m (outside the catalog).
    """

    scale: float = 1.0
    bias: np.ndarray | None = None
    noise_k: float = 0.0
    logistic: tuple | None = None
    label_drop: dict = field(default_factory=dict)
    range_dropout: tuple | None = None
    random_drop: float = 0.0
    elevation: np.ndarray | None = None
    mount: tuple | None = None
    velocity: tuple | None = None
    mixed: tuple | None = None
    echo: tuple | None = None
    weak: tuple | None = None
    near: tuple | None = None
    step: float = 0.0
    drift: float = 0.0
    walk: float = 0.0


def street_log(hidden: Hidden, sweeps: int = 12, columns: int = 900, seed: int = 0, sigma: float = SIGMA) -> dict:
    """Simulate ``sweeps`` sweeps with the ``hidden`` effects (``sigma``: the range noise, m).

    Returns:
        The arrays of a ``mi_lidar`` log: ``poses`` (S, 4, 4), ``directions`` (1, 16, W, 3),
        ``ranges`` (S, 16, W, NaN = miss), ``hit`` and ``times`` (S, 16, W).
    """
    rng = np.random.default_rng(seed)
    azimuth = 2 * np.pi * np.arange(columns) / columns
    elevation, azim = np.meshgrid(ELEVATIONS, azimuth, indexing="ij")  # (16, W)
    nominal_dirs = np.stack([np.cos(elevation) * np.cos(azim), np.cos(elevation) * np.sin(azim), np.sin(elevation)], -1)
    true_elev = elevation + (0.0 if hidden.elevation is None else np.asarray(hidden.elevation)[:, None])
    mount = np.zeros(6) if hidden.mount is None else np.asarray(hidden.mount, float)
    mount_rot = rotation(*mount[:3])
    beam = np.repeat(np.arange(16), columns)
    poses, ranges, times = [], [], []
    for s in range(sweeps):
        t0 = s * PERIOD
        yaw = 0.04 * np.sin(1.3 * s)
        pose = np.eye(4)
        pose[:3, :3] = rotation(0, 0, yaw)
        pose[:3, 3] = (-6.0 + SPEED * t0, 0.3 * np.sin(0.7 * s), HEIGHT)
        poses.append(pose)
        dt = np.repeat((np.arange(columns) / columns * PERIOD)[None], 16, 0).ravel()
        times.append(t0 + dt.reshape(16, columns))
        true_pose_rot = pose[:3, :3] @ mount_rot
        shift = np.zeros((dt.size, 3)) if hidden.velocity is None else dt[:, None] * np.asarray(hidden.velocity)
        origin = pose[:3, 3] + (pose[:3, :3] @ (mount[3:][None] + shift).T).T

        def directions(d_elev: float, d_azim: float, true_pose_rot=true_pose_rot) -> np.ndarray:
            e, a = (true_elev + d_elev).ravel(), (azim + d_azim).ravel()
            local = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
            return local @ true_pose_rot.T

        n = beam.size
        direction = directions(0.0, 0.0)
        if hidden.mixed is None and hidden.echo is None:
            r, normal, label = cast(origin, direction)
        else:
            divergence = (hidden.mixed or hidden.echo)[0]
            subs = [cast(origin, directions(e * divergence, a * divergence)) for e, a in MIXED_OFFSETS]
            sub_r = np.stack([x[0] for x in subs])  # (5, n)
            if hidden.mixed is not None:
                w = np.where(np.isfinite(sub_r), np.asarray(MIXED_WEIGHTS)[:, None], 0.0)
                total = w.sum(0)
                share_of = np.cumsum(w / np.maximum(total, 1e-12), axis=0)
                pick = np.minimum((share_of < rng.random(n)).sum(0), 4)  # one sub-ray, chosen by energy
                weighted = (w * np.where(np.isfinite(sub_r), sub_r, 0)).sum(0)
                mixed_range = np.where(total > 0, weighted / np.maximum(total, 1e-12), np.inf)
                in_between = rng.random(n) < hidden.mixed[1]
                r = np.where(in_between, mixed_range, sub_r[pick, np.arange(n)])
                _, normal, label = subs[0]
            else:  # the nearest or farthest surface the footprint meets
                first = hidden.echo[1] == "first"
                key = np.where(np.isfinite(sub_r), sub_r, np.inf if first else -np.inf)
                pick = np.argmin(key, axis=0) if first else np.argmax(key, axis=0)
                r = sub_r[pick, np.arange(n)]
                normal = np.stack([x[1] for x in subs])[pick, np.arange(n)]
                label = np.stack([x[2] for x in subs])[pick, np.arange(n)]
        cos_inc = np.abs(np.sum(normal * direction, axis=1))
        keep = np.isfinite(r)
        if hidden.logistic is not None:
            angle50, width = hidden.logistic
            delta = np.degrees(np.arccos(np.clip(cos_inc, 0, 1)))
            keep &= rng.random(n) >= 1 / (1 + np.exp(-(delta - angle50) / width))
        for lab, p in hidden.label_drop.items():
            keep &= ~((label == lab) & (rng.random(n) < p))
        if hidden.range_dropout is not None:
            rate, power = hidden.range_dropout
            keep &= rng.random(n) < np.exp(-rate * (np.where(np.isfinite(r), r, 0) / 10.0) ** power)
        keep &= rng.random(n) >= hidden.random_drop
        if hidden.weak is not None:
            range50, width = hidden.weak
            rho = np.array([REFLECTIVITY.get(k, 0.0) for k in range(max(REFLECTIVITY) + 1)])[label.astype(int)]
            power = rho * np.maximum(cos_inc, 1e-6) / np.where(np.isfinite(r), r, 1.0) ** 2
            keep &= rng.random(n) < 1 / (1 + np.exp(-(np.log(power) + 2 * np.log(range50)) / width))
        bias = 0.0 if hidden.bias is None else np.asarray(hidden.bias)[beam]
        noise = np.sqrt(sigma**2 + (hidden.noise_k * np.where(np.isfinite(r), r, 0)) ** 2)
        z = hidden.scale * np.where(keep, r, 0.0) + bias + hidden.drift * (t0 + dt) + rng.normal(0, 1, n) * noise
        if hidden.walk > 0:
            z = z + rng.exponential(hidden.walk, n)
        if hidden.near is not None:
            p_near, scale = hidden.near
            clutter = rng.random(n) < p_near
            z = np.where(clutter, np.abs(rng.normal(0, scale, n)), z)
            keep |= clutter
        if hidden.step > 0:
            z = np.round(z / hidden.step) * hidden.step
        hit = keep & (z > 0) & (z <= MAX_RANGE)
        ranges.append(np.where(hit, z, np.nan).reshape(16, columns))
    return {
        "poses": np.stack(poses),
        "directions": nominal_dirs[None].astype(np.float32),
        "ranges": np.stack(ranges).astype(np.float32),
        "hit": np.isfinite(np.stack(ranges)),
        "times": np.stack(times),
    }
