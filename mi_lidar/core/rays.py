"""The rays of a log as :class:`~mi_lidar.core.effects.RayBatch` wavefronts, with their measurements.

One builder for every consumer of logs (the loop's comparison, diagnosis and fitting, and the
calibration layer): a :class:`~mi_lidar.core.log.Log` is flattened once into per-ray indices, and any
subset of its rays becomes a world-frame :class:`RayBatch` plus the measured ranges and return
flags. Every array handed to Dr.Jit is 64-byte aligned (:func:`mi_lidar.core.arrays.aligned`): Dr.Jit
wraps numpy memory and compiles aligned and unaligned loads into different kernels, so unaligned
batches would recompile the same likelihood kernels at random.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.frames import scene_origin
from mi_lidar.core.log import Log


def world_rays(log: Log, scan: np.ndarray, beam: np.ndarray, column: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) origins (m) and unit directions of rays ``(scan, beam, column)`` of ``log`` in the world frame
    (each scan's pose applied), numpy."""
    pattern = np.minimum(scan, log.directions.shape[0] - 1)
    d = log.directions[pattern, beam, column]
    origins = np.zeros_like(log.directions) if log.origins is None else log.origins
    o = np.broadcast_to(origins, log.directions.shape)[pattern, beam, column]
    rotation, translation = log.poses[scan, :3, :3], log.poses[scan, :3, 3]
    return np.einsum("nij,nj->ni", rotation, o) + translation, np.einsum("nij,nj->ni", rotation, d)


@dataclass
class RayBatch:
    """A wavefront of Lidar rays (one lane per ray).

    Attributes:
        origin: ray origins in the world frame, m.
        direction: unit ray directions in the world frame.
        beam: beam (range-image row) index of each ray.
        time: time of each ray since the start of its sweep (its scan's first ray, the time of the
            scan's pose), s: small, so float32 keeps microseconds in logs of any length.
        ray_id: unique index of each ray (keys the random streams).
        sensor_rotation: optional sensor-to-world rotation of each ray's sensor pose (effects
            that act in the sensor frame, such as beam angle offsets and extrinsics, use it;
            None means the world axes).
        sensor_position: optional sensor position in the world frame, m (None: the ray origin).
    """

    origin: mi.Point3f
    direction: mi.Vector3f
    beam: mi.UInt32
    time: mi.Float
    ray_id: mi.UInt32
    sensor_rotation: mi.Matrix3f | None = None
    sensor_position: mi.Point3f | None = None

    def __post_init__(self):
        """Broadcast fields given with one lane (a shared origin, say) to the batch width."""
        fields = [
            f
            for f in ("origin", "direction", "beam", "time", "ray_id", "sensor_rotation", "sensor_position")
            if getattr(self, f) is not None
        ]
        n = max(dr.width(getattr(self, f)) for f in fields)
        for f in fields:
            value = getattr(self, f)
            if dr.width(value) == 1 and n > 1:
                setattr(self, f, dr.gather(type(value), value, dr.zeros(mi.UInt32, n)))

    @property
    def width(self) -> int:
        """Number of rays."""
        return dr.width(self.ray_id)

    def sensor_frame(self) -> tuple[mi.Matrix3f, mi.Point3f]:
        """Sensor-to-world rotation and sensor position (m) of each lane.

        Without ``sensor_rotation`` the world axes stand in for the sensor's; without
        ``sensor_position`` the ray origin does.
        """
        rotation = mi.Matrix3f(1.0) if self.sensor_rotation is None else self.sensor_rotation
        position = self.origin if self.sensor_position is None else self.sensor_position
        return rotation, position

    def take(self, index: mi.UInt32) -> RayBatch:
        """The sub-batch of lanes ``index``."""
        return RayBatch(
            origin=dr.gather(mi.Point3f, self.origin, index),
            direction=dr.gather(mi.Vector3f, self.direction, index),
            beam=dr.gather(mi.UInt32, self.beam, index),
            time=dr.gather(mi.Float, self.time, index),
            ray_id=dr.gather(mi.UInt32, self.ray_id, index),
            sensor_rotation=None
            if self.sensor_rotation is None
            else dr.gather(mi.Matrix3f, self.sensor_rotation, index),
            sensor_position=None
            if self.sensor_position is None
            else dr.gather(mi.Point3f, self.sensor_position, index),
        )


@dataclass
class LogRays:
    """Every ray of a log, flattened in (scan, beam, firing) order (ray ``i`` is ``log.ranges.ravel()[i]``).

    Attributes:
        log: the log.
        scan, beam, column: (N,) indices of each ray in the (S, H, W) grid.
        time: (N,) ray timestamps, s (relative to the first ray of the log, or absolute); the
            :class:`RayBatch` of :meth:`batch` gets the time since each ray's sweep start instead.
        measured: (N,) measured range, m (NaN for a miss).
        hit: (N,) True where the sensor reported a return.
        intensity: optional (N,) measured intensities (sensor units, NaN for a miss) that the
            likelihood scores with the range (None: ranges only).
        origin: (3,) world position (m) of the scene's local frame, subtracted from the poses before
            the rays reach float32 (:func:`mi_lidar.core.frames.scene_origin`; zero: world coordinates).
    """

    log: Log
    scan: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    time: np.ndarray
    measured: np.ndarray
    hit: np.ndarray
    intensity: np.ndarray | None = None
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_log(cls, log: Log, relative_time: bool = True, intensity: str | None = None, scene=None) -> LogRays:
        """Flatten a log.

        Args:
            log: the log.
            relative_time: give times relative to the log's first ray (float32 then keeps
                microseconds); False keeps the log's absolute timestamps.
            intensity: name of the per-ray attribute holding the measured intensity to score
                (``intensity``, or an Ouster log's ``reflectivity`` or ``signal``); None scores ranges only.
            scene: the scene the rays will be traced in: a scene loaded at a local origin (georeferenced)
                gets the rays in its frame. None: world coordinates.
        """
        if intensity is not None and intensity not in log.attributes:
            raise LogFormatError(
                f"the log has no intensity attribute {intensity!r}; it has {sorted(log.attributes)}: "
                "pick one of those or score ranges only"
            )
        s, h, w = log.shape
        scan, beam, column = (a.ravel() for a in np.meshgrid(np.arange(s), np.arange(h), np.arange(w), indexing="ij"))
        times = log.times - log.times.reshape(-1)[0] if relative_time else log.times
        return cls(
            log=log,
            scan=scan,
            beam=beam,
            column=column,
            time=times.ravel(),
            measured=log.ranges.ravel().astype(np.float32),
            hit=log.hit.ravel(),
            intensity=None
            if intensity is None
            else np.where(log.hit, log.attributes[intensity], np.nan).ravel().astype(np.float32),
            origin=np.zeros(3) if scene is None else scene_origin(scene),
        )

    @cached_property
    def _sweep_start(self) -> np.ndarray:
        """(S,) absolute timestamp of each scan's first ray, s (the time of its pose), float64."""
        return self.log.times.reshape(self.log.shape[0], -1).min(axis=1)

    @property
    def n(self) -> int:
        """Number of rays."""
        return int(self.hit.size)

    def batch(self, index: np.ndarray | None = None) -> tuple[RayBatch, mi.Float, mi.Bool]:
        """World-frame rays, measured ranges and hit flags of rays ``index`` (all when None).

        Returns:
            ``(rays, measured, hit)``: the rays in the scene's frame (ray ids are the flat indices into the log, the
            ids :func:`mi_lidar.simulate` gives), (M,) measured ranges in m (0 for a miss) and (M,)
            return flags.
        """
        index = np.arange(self.n) if index is None else np.asarray(index)
        scan, beam, column = self.scan[index], self.beam[index], self.column[index]
        log = self.log
        pick = lambda a: a[scan if a.shape[0] > 1 else 0, beam, column].astype(np.float64)
        rotation = log.poses[scan, :3, :3]
        position = log.poses[scan, :3, 3] - self.origin  # in the scene's frame, before float32
        direction = np.einsum("nij,nj->ni", rotation, pick(log.directions))
        origin = np.einsum("nij,nj->ni", rotation, pick(log.origins)) + position

        def floats(columns: np.ndarray) -> list[mi.Float]:
            return [mi.Float(aligned(c.astype(np.float32))) for c in columns]

        rays = RayBatch(
            origin=mi.Point3f(*floats(origin.T)),
            direction=dr.normalize(mi.Vector3f(*floats(direction.T))),
            beam=mi.UInt32(aligned(beam.astype(np.uint32))),
            time=mi.Float(aligned((log.times[scan, beam, column] - self._sweep_start[scan]).astype(np.float32))),
            ray_id=mi.UInt32(aligned(index.astype(np.uint32))),
            sensor_rotation=mi.Matrix3f(*floats(rotation.reshape(-1, 9).T)),
            sensor_position=mi.Point3f(*floats(position.T)),
        )
        measured = np.where(self.hit[index], self.measured[index], 0.0).astype(np.float32)
        return rays, mi.Float(aligned(measured)), mi.Bool(aligned(self.hit[index]))

    def measured_intensity(self, index: np.ndarray | None = None) -> mi.Float | None:
        """(M,) measured intensities of rays ``index`` (all when None; NaN for misses), or None when not scored."""
        if self.intensity is None:
            return None
        index = np.arange(self.n) if index is None else np.asarray(index)
        return mi.Float(aligned(self.intensity[index]))
