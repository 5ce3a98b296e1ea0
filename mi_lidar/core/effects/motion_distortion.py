"""Motion distortion: the sensor moves during a sweep, so each ray leaves from its own pose."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch


def rotate(axis_angle: mi.Vector3f, v: mi.Vector3f) -> mi.Vector3f:
    """Rotate ``v`` by the rotation vector ``axis_angle`` (rad) with Rodrigues' formula."""
    angle = dr.norm(axis_angle)
    k = axis_angle / dr.maximum(angle, 1e-12)
    c, s = dr.cos(angle), dr.sin(angle)
    rotated = v * c + dr.cross(k, v) * s + k * dr.dot(k, v) * (1.0 - c)
    return dr.select(angle > 1e-12, rotated, v + dr.cross(axis_angle, v))


@register_effect
class MotionDistortion(Effect):
    """Constant sensor velocity during a sweep, from per-ray timestamps.

    Log poses are the sensor pose at the start of each sweep. A ray fired ``dt`` seconds later
    leaves from the pose moved by the linear velocity ``(vx, vy, vz)`` (m/s) and turned by the
    angular velocity ``(wx, wy, wz)`` (rad/s), both in the sensor frame at sweep start:
    ``o' = p + R (v dt + Rot(w dt) R^T (o - p))`` and ``d' = R Rot(w dt) R^T d``.
    ``dt`` is the ray's time since its sweep start (:attr:`~mi_lidar.core.rays.RayBatch.time`,
    whatever the scans' start times, so real logs whose sweeps drift against a fixed period are
    right), wrapped by ``period`` (s) for scans that hold several sweeps. Rays of a log without
    per-ray times (one timestamp per scan, as in CARMEN logs) have ``dt = 0``: no distortion. The
    six velocities are differentiable; ``period`` is fixed.

    Example: ``motion_distortion(vx=10, wz=0.5, period=0.1)`` (10 m/s forward, turning left).
    """

    name = "motion_distortion"
    specs = {
        **{
            f"v{a}": ParamSpec(
                0.0, "m/s", f"linear velocity along sensor {a}", lower=-100.0, upper=100.0, fit_scale=1.0
            )
            for a in "xyz"
        },
        **{
            f"w{a}": ParamSpec(
                0.0, "rad/s", f"angular velocity about sensor {a}", lower=-20.0, upper=20.0, fit_scale=0.05
            )
            for a in "xyz"
        },
        "period": ParamSpec(0.1, "s", "sweep period (sweeps start at its multiples)", lower=1e-6, upper=1e3, fit=False),
    }

    def perturb_rays(self, rays: RayBatch) -> RayBatch:
        period = self["period"]
        dt = rays.time - dr.floor(rays.time / period + 1e-5) * period  # 1e-5: a float32 time of one period
        rotation, position = rays.sensor_frame()
        turn = mi.Vector3f(self["wx"], self["wy"], self["wz"]) * dt
        shift = mi.Vector3f(self["vx"], self["vy"], self["vz"]) * dt
        inverse = rotation.T
        origin = position + mi.Vector3f(
            rotation @ (shift + rotate(turn, mi.Vector3f(inverse @ (rays.origin - position))))
        )
        direction = mi.Vector3f(rotation @ rotate(turn, mi.Vector3f(inverse @ rays.direction)))
        return RayBatch(
            origin=mi.Point3f(origin),
            direction=dr.normalize(direction),
            beam=rays.beam,
            time=rays.time,
            ray_id=rays.ray_id,
            sensor_rotation=rays.sensor_rotation,
            sensor_position=rays.sensor_position,
        )
