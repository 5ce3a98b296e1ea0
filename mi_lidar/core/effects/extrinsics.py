"""Extrinsics: a small rigid offset between the pose given for the sensor and its true pose."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch


def rotate_vector(omega: mi.Vector3f, v: mi.Vector3f) -> mi.Vector3f:
    """Rotate ``v`` by the rotation vector ``omega`` (axis times angle, rad): ``exp([omega]x) v``.

    Rodrigues' formula written as ``v + a (w x v) + b w x (w x v)`` with ``a = sin t / t`` and
    ``b = 2 sin^2(t/2) / t^2``, which stays finite and differentiable at ``omega = 0``.
    """
    theta2 = dr.squared_norm(omega)
    theta = dr.sqrt(dr.maximum(theta2, 1e-24))
    a = dr.sin(theta) / theta
    half = dr.sin(0.5 * theta) / theta
    b = 2.0 * half * half
    wxv = dr.cross(omega, v)
    return v + a * wxv + b * dr.cross(omega, wxv)


@register_effect
class Extrinsics(Effect):
    """Offset ``T = (exp([r]x), t)`` of the true sensor pose relative to the given one.

    With the given sensor-to-world pose ``(R, p)``, the true pose is ``(R, p) * T``: a ray with
    sensor-frame origin ``o`` and direction ``d`` starts at ``p + R (exp([r]x) o + t)`` and points
    along ``R exp([r]x) d``. The rotation vector ``r = (rx, ry, rz)`` (rad) and the translation
    ``t = (tx, ty, tz)`` (m) are in the sensor frame. The pose comes from
    :attr:`RayBatch.sensor_rotation` and :attr:`RayBatch.sensor_position` (world axes at the ray
    origin when the batch has none). All six parameters are differentiable.

    Example: ``extrinsics(rz=0.01, tx=0.05)``.
    """

    name = "extrinsics"
    specs = {
        **{
            f"r{axis}": ParamSpec(
                0.0,
                "rad",
                f"rotation vector, {axis} component (sensor frame)",
                lower=-0.5,
                upper=0.5,
                fit_scale=0.005,  # about 0.3 deg: a mounting error converges from zero in tenths of a degree
            )
            for axis in "xyz"
        },
        **{
            f"t{axis}": ParamSpec(
                0.0, "m", f"translation, {axis} component (sensor frame)", lower=-10.0, upper=10.0, fit_scale=0.02
            )
            for axis in "xyz"
        },
    }

    def perturb_rays(self, rays: RayBatch) -> RayBatch:
        rotation, position = rays.sensor_frame()
        inverse = rotation.T
        omega = mi.Vector3f(self["rx"], self["ry"], self["rz"])
        translation = mi.Vector3f(self["tx"], self["ty"], self["tz"])
        local_origin = mi.Vector3f(inverse @ (rays.origin - position))
        origin = mi.Point3f(position + rotation @ (rotate_vector(omega, local_origin) + translation))
        direction = mi.Vector3f(rotation @ rotate_vector(omega, mi.Vector3f(inverse @ rays.direction)))
        return RayBatch(
            origin=origin,
            direction=direction,
            beam=rays.beam,
            time=rays.time,
            ray_id=rays.ray_id,
            sensor_rotation=rays.sensor_rotation,
            sensor_position=rays.sensor_position,
        )
