"""The fast path: simulate scans of a scene from a firing pattern and sensor poses."""

from __future__ import annotations

import os
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.channels import channels_to_numpy
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import PatternError, PoseError
from mi_lidar.core.frames import COORDINATES_DOC, check_float32, scene_origin, shift_poses
from mi_lidar.core.log import Log
from mi_lidar.core.poses import validate_poses
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.loading import load_scene, scene_lidar_sensor, scene_sensor_model

MAX_RAYS_PER_BATCH = 1 << 22  # rays traced at once (bounds peak memory)
_PATTERN_RAYS: dict[int, tuple] = {}  # id(pattern) -> its rays, while the pattern lives


def pattern_rays(pattern) -> tuple[np.ndarray, np.ndarray, mi.Vector3f, mi.Point3f]:
    """The sensor-frame rays of ``pattern``, computed once per pattern object.

    Returns:
        ``(directions, origins, local_d, local_o)``: (H, W, 3) float32 numpy arrays (read-only, shared
        by every log simulated with the pattern) and the same rays as Dr.Jit arrays (one lane per ray).
    """
    key = id(pattern)
    if key not in _PATTERN_RAYS:
        directions, origins = pattern.directions(), pattern.origins()
        directions.setflags(write=False)
        origins.setflags(write=False)
        local_d = mi.Vector3f(*(aligned(c) for c in directions.reshape(-1, 3).T))
        local_o = mi.Point3f(*(aligned(c) for c in origins.reshape(-1, 3).T))
        _PATTERN_RAYS[key] = (directions, origins, local_d, local_o)
        weakref.finalize(pattern, _PATTERN_RAYS.pop, key, None)
    return _PATTERN_RAYS[key]


def pose_entries(poses: np.ndarray, scan: mi.UInt32) -> list[mi.Float]:
    """The 16 row-major entries of each lane's pose: ``poses[scan]`` gathered in Dr.Jit."""
    table = poses.astype(np.float32)
    return [dr.gather(mi.Float, mi.Float(aligned(table[:, i, j])), scan) for i in range(4) for j in range(4)]


def world_rays(local_origin: mi.Point3f, local_direction: mi.Vector3f, entries: list, index: mi.UInt32):
    """World-frame origins and unit directions of pattern rays ``index`` under per-lane poses.

    Uses the same Dr.Jit transform arithmetic as the ``lidar`` sensor's ``sample_ray``, so the
    fast path and ``mi.render`` trace bit-identical rays.

    Args:
        local_origin, local_direction: the pattern's rays in the sensor frame (one lane per ray).
        entries: 16 row-major pose entries per lane (:func:`pose_entries`).
        index: pattern ray of each lane.
    """
    to_world = mi.Transform4f(mi.Matrix4f(*entries))
    origin = to_world @ dr.gather(mi.Point3f, local_origin, index)
    direction = dr.normalize(to_world @ dr.gather(mi.Vector3f, local_direction, index))
    return origin, direction


def scene_poses(poses: np.ndarray, origin: np.ndarray, source: str = "poses") -> np.ndarray:
    """World poses (S, 4, 4) in the frame of a scene whose local origin is ``origin`` (3,) m, float64.

    Raises:
        PoseError: a pose that even in the scene's frame lies where float32 keeps more than 1 mm
            (poses in another frame than the scene's).
    """
    local = shift_poses(poses, origin)
    where = "" if not np.any(origin) else f" (the scene's local origin is {', '.join(f'{v:,.0f}' for v in origin)})"
    check_float32(
        local[:, :3, 3],
        source,
        f"sensor positions relative to the scene{where}",
        f"Give the poses in the scene's frame, or place the scene where the poses are (see {COORDINATES_DOC})",
        PoseError,
    )
    return local


def simulate(
    scene, pattern=None, poses=None, seed: int = 0, model: SensorModel | None = None, scan_times=None, progress=None
) -> Log:
    """Simulate one scan per pose and return them as a :class:`~mi_lidar.core.log.Log`.

    Args:
        scene: a loaded Mitsuba scene, or the path of a scene XML.
        pattern: a :class:`~mi_lidar.core.patterns.FiringPattern` or a pattern name/path; default:
            the pattern of the scene's ``lidar`` sensor.
        poses: (4, 4) or (S, 4, 4) sensor-to-world transforms in the world frame, float64 (a scene
            loaded at a local origin gets them moved into its frame, and the log keeps them as given);
            default: the scene's ``lidar`` sensor pose, or the identity.
        seed: random seed; scan ``s`` uses rays ``s * H * W ...``, so scans are independent.
        model: sensor model; default: the scene's ``lidar`` sensor and integrator settings.
        scan_times: (S,) start time of each sweep (s); default ``s * pattern.period``.
        progress: optional callable ``progress(done_scans, total_scans)``.

    Returns:
        A log of S scans with channels ``element_id``, ``shape_id``, ``label``,
        ``cos_incidence``, ``nominal_range`` and ``segments`` as attributes.
    """
    from mi_lidar.core.patterns import FiringPattern, get_pattern

    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)
    if pattern is None:
        sensor = scene_lidar_sensor(scene)
        if sensor is None:
            raise PatternError(
                "the scene has no `lidar` sensor to take a firing pattern from; pass pattern='vlp16' (or another name)"
            )
        pattern = sensor.pattern
    if not isinstance(pattern, FiringPattern):
        pattern = get_pattern(str(pattern))
    default_model, default_pose = scene_sensor_model(scene)
    model = model or default_model
    origin = scene_origin(scene)
    poses = validate_poses(shift_poses(default_pose, -origin) if poses is None else poses)
    local = scene_poses(poses, origin)
    n_scans = len(poses)
    height, width = pattern.shape
    n = height * width
    if scan_times is None:
        scan_times = np.arange(n_scans) * pattern.period
    scan_times = np.asarray(scan_times, dtype=np.float64)
    if scan_times.shape != (n_scans,):
        raise ValueError(f"scan_times has shape {scan_times.shape}; expected ({n_scans},) to match the poses")

    table = ElementTable.from_scene(scene)
    directions, origins, local_d, local_o = pattern_rays(pattern)
    ray_in_scan = dr.arange(mi.UInt32, n)
    beam = mi.UInt32(np.repeat(np.arange(height, dtype=np.uint32), width))
    rel_time = pattern.time.reshape(-1)
    channels: dict[str, list] = {}
    per_batch = max(1, MAX_RAYS_PER_BATCH // n)
    for first in range(0, n_scans, per_batch):
        batch = range(first, min(first + per_batch, n_scans))
        scan = dr.repeat(dr.arange(mi.UInt32, batch.start, batch.stop), n)
        entries = pose_entries(local, scan)
        rays = RayBatch(
            *world_rays(local_o, local_d, entries, dr.tile(ray_in_scan, len(batch))),
            beam=dr.tile(beam, len(batch)),
            time=mi.Float(aligned(np.tile(rel_time, len(batch)).astype(np.float32))),  # since the sweep start
            ray_id=dr.arange(mi.UInt32, batch.start * n, batch.stop * n),
            sensor_rotation=mi.Matrix3f(*(entries[4 * i + j] for i in range(3) for j in range(3))),
            sensor_position=mi.Point3f(entries[3], entries[7], entries[11]),
        )
        out = channels_to_numpy(model.simulate_rays(scene, table, rays, seed))
        for name, value in out.items():
            channels.setdefault(name, []).append(value.reshape(len(batch), height, width))
        if progress is not None:
            progress(batch.stop, n_scans)
    merged = {name: values[0] if len(values) == 1 else np.concatenate(values) for name, values in channels.items()}
    times = scan_times[:, None, None] + rel_time.reshape(1, height, width)
    return Log(
        poses=poses,
        directions=directions[None],
        origins=origins[None],
        ranges=merged.pop("range"),
        hit=merged.pop("hit"),
        times=times,
        attributes=merged,
        sensor={
            "pattern": pattern.name,
            "min_range": model.min_range,
            "max_range": model.max_range,
            "range_sigma": model.range_sigma,
            "max_segments": model.max_segments,
            "effects": [e.describe() for e in model.effects],
            "seed": int(seed),
        },
    )
