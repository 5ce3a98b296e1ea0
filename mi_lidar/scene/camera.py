"""Camera and Lidar from one scene: synchronized images, scans and the calibration that ties them.

The same scene XML serves both sensors: ``lidar_material`` carries a diffuse ``reflectance`` for
cameras next to its Lidar values, and emitters in the scene light the camera image (the Lidar
ignores them). :func:`camera_lidar_frame` renders a path-traced RGB image from a pinhole camera
and a Lidar scan from the scene's ``lidar`` sensor, and projects the Lidar returns into the
image (KITTI-style: image, points in the camera frame, intrinsics and extrinsics).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.frames import scene_origin, shift_poses


@dataclass
class PinholeCamera:
    """A pinhole camera (Mitsuba's ``perspective`` sensor).

    Attributes:
        to_world: (4, 4) camera-to-world transform in Mitsuba's convention (camera looks along
            +z, x left, y up in its own frame).
        width, height: image size, pixels.
        fov_deg: horizontal field of view, degrees (square pixels: one focal length).
        principal_point: (cx, cy) pixels, or None for the image centre. Pixel coordinates put
            (0, 0) at the top-left corner of the image, so pixel (i, j) spans [i, i+1) x [j, j+1)
            (OpenCV's integer-centred coordinates are these minus 0.5).
    """

    to_world: np.ndarray
    width: int = 640
    height: int = 400
    fov_deg: float = 70.0
    principal_point: tuple[float, float] | None = None

    def __post_init__(self):
        if not (self.width > 0 and self.height > 0 and 0 < self.fov_deg < 180):
            raise ParameterError(
                f"camera: need width, height > 0 and 0 < fov_deg < 180; got {self.width}, {self.height}, {self.fov_deg}"
            )
        if self.principal_point is not None:
            cx, cy = self.principal_point
            if not (0 < cx < self.width and 0 < cy < self.height):
                raise ParameterError(
                    f"camera: principal point ({cx}, {cy}) lies outside the {self.width} x {self.height} image; "
                    "give it in pixels from the top-left corner"
                )

    @classmethod
    def look_at(cls, origin, target, up=(0.0, 0.0, 1.0), **kwargs) -> PinholeCamera:
        """A camera at ``origin`` (m) looking at ``target`` (m)."""
        origin, target, up = (list(map(float, v)) for v in (origin, target, up))
        offset = np.array(target) - origin  # the rotation from a float64 difference, the position kept in float64
        to_world = np.array(mi.ScalarTransform4f().look_at(origin=[0.0] * 3, target=offset, up=up).matrix, np.float64)
        to_world[:3, 3] = origin
        if not np.isfinite(to_world).all():
            raise ParameterError(
                f"camera at {origin} looking at {target}: the target must differ from the position and not lie "
                f"straight along the image's up {up}; move the target"
            )
        return cls(to_world=to_world, **kwargs)

    @property
    def intrinsics(self) -> np.ndarray:
        """(3, 3) pixel intrinsics K for the OpenCV convention (x right, y down, z forward)."""
        f = 0.5 * self.width / math.tan(math.radians(self.fov_deg) / 2)
        cx, cy = self.centre
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])

    @property
    def centre(self) -> tuple[float, float]:
        """The principal point (cx, cy), pixels."""
        return self.principal_point or (self.width / 2, self.height / 2)

    @property
    def world_to_opencv(self) -> np.ndarray:
        """(4, 4) world-to-camera transform in the OpenCV convention."""
        flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # Mitsuba camera frame (x left, y up) -> OpenCV (x right, y down)
        return flip @ np.linalg.inv(self.to_world)

    def sensor(self, spp: int = 64, origin=(0.0, 0.0, 0.0)):
        """The Mitsuba ``perspective`` sensor of this camera, in the frame of a scene whose local origin is
        ``origin`` (3,) m (:func:`mi_lidar.core.frames.scene_origin`; moved in float64, before float32)."""
        cx, cy = self.centre
        to_world = shift_poses(self.to_world, origin)
        return mi.load_dict(
            {
                "type": "perspective",
                "fov": float(self.fov_deg),
                "fov_axis": "x",
                # Mitsuba's offsets are fractions of the film, positive towards image left and up
                "principal_point_offset_x": float(self.width / 2 - cx) / self.width,
                "principal_point_offset_y": float(self.height / 2 - cy) / self.height,
                "to_world": mi.ScalarTransform4f(to_world.astype(np.float32)),
                "film": {
                    "type": "hdrfilm",
                    "width": int(self.width),
                    "height": int(self.height),
                    "pixel_format": "rgb",
                    "rfilter": {"type": "box"},
                },
                "sampler": {"type": "independent", "sample_count": int(spp)},
            }
        )

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project (N, 3) world points (m) to pixels.

        Returns:
            ``(uv, depth, visible)``: (N, 2) pixel coordinates, (N,) depth along the optical axis
            (m) and (N,) True where the point is in front of the camera and inside the image.
        """
        p = np.c_[points_world, np.ones(len(points_world))] @ self.world_to_opencv.T
        depth = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (p[:, :3] @ self.intrinsics.T)[:, :2] / depth[:, None]
        visible = (
            (depth > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)
        )
        return uv, depth, visible


def render_camera(scene, camera: PinholeCamera, spp: int = 64, seed: int = 0) -> np.ndarray:
    """Path-trace the camera's (height, width, 3) linear RGB image of ``scene``.

    The image is the mean of ``spp`` passes of one sample per pixel (their seeds drawn from
    ``SeedSequence(seed)``), summed in pass order: with the box filter each pass writes every pixel once, so
    the image is bit-identical whatever the thread count or scheduling (samples of one pixel
    accumulated by concurrent threads are not).
    """
    sensor = camera.sensor(1, origin=scene_origin(scene))  # a georeferenced scene is loaded at a local origin
    integrator = mi.load_dict({"type": "path", "max_depth": 6})
    seeds = np.random.SeedSequence(seed).generate_state(spp) & 0x7FFFFFFF
    image = np.zeros((camera.height, camera.width, 3), dtype=np.float64)
    for pass_seed in seeds:
        image += np.asarray(mi.render(scene, sensor=sensor, integrator=integrator, seed=int(pass_seed)))
    return (image / spp).astype(np.float32)


def camera_lidar_frame(scene, camera: PinholeCamera, seed: int = 0, spp: int = 64) -> dict:
    """One synchronized camera image and Lidar scan of ``scene``, with the Lidar points projected.

    Returns:
        Dict with ``image`` (H, W, 3) linear RGB, ``log`` (the one-scan Lidar
        :class:`~mi_lidar.core.log.Log`), ``points`` (N, 3) world-frame returns (m), ``uv`` (N, 2),
        ``depth`` (N,) m and ``visible`` (N,) for the projection, ``K`` (3, 3) and
        ``lidar_to_camera`` (4, 4, OpenCV camera frame).
    """
    from mi_lidar.scene.simulation import simulate

    log = simulate(scene, seed=seed)
    points = log.points_world()[0][log.hit[0]]
    uv, depth, visible = camera.project(points)
    return {
        "image": render_camera(scene, camera, spp=spp, seed=seed),
        "log": log,
        "points": points,
        "uv": uv,
        "depth": depth,
        "visible": visible,
        "K": camera.intrinsics,
        "lidar_to_camera": camera.world_to_opencv @ log.poses[0],
    }
