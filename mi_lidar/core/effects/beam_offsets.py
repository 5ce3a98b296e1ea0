"""Per-beam angle offsets: the intrinsic calibration error of a multi-beam Lidar's firing table."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.effects.base import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch


def offset_direction(local: mi.Vector3f, d_elevation: mi.Float, d_azimuth: mi.Float) -> mi.Vector3f:
    """Turn sensor-frame unit directions up by ``d_elevation`` and counter-clockwise by ``d_azimuth``.

    Args:
        local: unit directions in the sensor frame (x forward, z up), one lane per ray.
        d_elevation: elevation offsets, rad (positive up).
        d_azimuth: azimuth offsets, rad (counter-clockwise about +z seen from above).

    Returns:
        The rotated unit directions. The rotation is smooth in both offsets, so their
        gradients exist everywhere except straight up or down.
    """
    horizontal = dr.sqrt(dr.maximum(dr.square(local.x) + dr.square(local.y), 1e-20))
    ux, uy = local.x / horizontal, local.y / horizontal  # horizontal unit vector of the beam
    ce, se = dr.cos(d_elevation), dr.sin(d_elevation)
    h = horizontal * ce - local.z * se  # horizontal length after tilting up
    z = local.z * ce + horizontal * se
    ca, sa = dr.cos(d_azimuth), dr.sin(d_azimuth)
    return mi.Vector3f(h * (ux * ca - uy * sa), h * (ux * sa + uy * ca), z)


@register_effect
class BeamOffsets(Effect):
    """Per-beam elevation and azimuth offsets added to the nominal firing table.

    Each ray of beam ``b`` is turned, in the sensor frame, up by ``elevation[b]`` and
    counter-clockwise about the sensor's z axis by ``azimuth[b]`` before tracing. Ray origins do
    not move. The sensor frame is taken from :attr:`RayBatch.sensor_rotation` (world axes when the
    batch has none). Both parameters are differentiable; in calibration they are recovered from
    the ranges they change (see ``mi_lidar.calibration``).

    Example: ``beam_offsets(elevation=[0.001 -0.002 0 0], azimuth=[0])`` (rad; the last value
    repeats for the remaining beams).
    """

    name = "beam_offsets"
    specs = {
        "elevation": ParamSpec(
            0.0,
            "rad",
            "elevation offset of each beam (positive up)",
            lower=-0.2,
            upper=0.2,
            per_beam=True,
            fit_scale=0.002,
        ),
        "azimuth": ParamSpec(
            0.0,
            "rad",
            "azimuth offset of each beam (counter-clockwise)",
            lower=-0.2,
            upper=0.2,
            per_beam=True,
            fit_scale=0.002,
        ),
    }

    def perturb_rays(self, rays: RayBatch) -> RayBatch:
        rotation, _ = rays.sensor_frame()
        local = mi.Vector3f(rotation.T @ rays.direction)
        turned = offset_direction(local, self.per_beam("elevation", rays.beam), self.per_beam("azimuth", rays.beam))
        return RayBatch(
            origin=rays.origin,
            direction=mi.Vector3f(rotation @ turned),
            beam=rays.beam,
            time=rays.time,
            ray_id=rays.ray_id,
            sensor_rotation=rays.sensor_rotation,
            sensor_position=rays.sensor_position,
        )
