"""The rays of a log as :class:`~mi_lidar.effects.RayBatch` wavefronts, with their measurements."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..effects.base import RayBatch
from ..log import Log


@dataclass
class LogRays:
    """Every ray of a log, flattened in (scan, beam, firing) order.

    Attributes:
        log: the log.
        scan, beam, column: (N,) indices of each ray in the (S, H, W) grid.
        time: (N,) ray timestamps relative to the first ray of the log, s.
        measured: (N,) measured range, m (NaN for a miss).
        hit: (N,) True where the sensor reported a return.
    """

    log: Log
    scan: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    time: np.ndarray
    measured: np.ndarray
    hit: np.ndarray

    @classmethod
    def from_log(cls, log: Log) -> "LogRays":
        """Flatten a log (times become relative to its first ray, so float32 keeps microseconds)."""
        s, h, w = log.shape
        scan, beam, column = (a.ravel() for a in np.meshgrid(np.arange(s), np.arange(h), np.arange(w), indexing="ij"))
        times = log.times - log.times.reshape(-1)[0]
        return cls(log=log, scan=scan, beam=beam, column=column, time=times.ravel(),
                   measured=log.ranges.ravel().astype(np.float32), hit=log.hit.ravel())

    @property
    def n(self) -> int:
        """Number of rays."""
        return int(self.hit.size)

    def batch(self, index: np.ndarray | None = None) -> tuple[RayBatch, mi.Float, mi.Bool]:
        """World-frame rays, measured ranges and hit flags of rays ``index`` (all when None).

        Ray ids are the flat indices into the log, the ids :func:`mi_lidar.simulate` gives.
        """
        index = np.arange(self.n) if index is None else np.asarray(index)
        scan, beam, column = self.scan[index], self.beam[index], self.column[index]
        log = self.log
        pick = (lambda a: a[scan if a.shape[0] > 1 else 0, beam, column].astype(np.float64))
        rotation = log.poses[scan, :3, :3]
        position = log.poses[scan, :3, 3]
        direction = np.einsum("nij,nj->ni", rotation, pick(log.directions))
        origin = np.einsum("nij,nj->ni", rotation, pick(log.origins)) + position
        rays = RayBatch(
            origin=mi.Point3f(*origin.T.astype(np.float32)),
            direction=dr.normalize(mi.Vector3f(*direction.T.astype(np.float32))),
            beam=mi.UInt32(beam.astype(np.uint32)),
            time=mi.Float(self.time[index].astype(np.float32)),
            ray_id=mi.UInt32(index.astype(np.uint32)),
            sensor_rotation=mi.Matrix3f(np.ascontiguousarray(rotation.transpose(1, 2, 0), dtype=np.float32)),
            sensor_position=mi.Point3f(*position.T.astype(np.float32)),
        )
        measured = np.where(self.hit[index], self.measured[index], 0.0).astype(np.float32)
        return rays, mi.Float(measured), mi.Bool(self.hit[index])
