"""The sensor rig of a dataset: Lidars and pinhole cameras mounted on the ego vehicle.

Frames: ego x forward, y left, z up (m). A Lidar's mount is its sensor-to-ego transform; a camera's
is its OpenCV optical frame (x right, y down, z forward) to ego. KITTI's calibration is written with
the first camera as the reference camera (``image_2``) and the first Lidar as ``velo``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import numpy as np

from mi_lidar.core.densities import ReturnDensity, parse_density
from mi_lidar.core.effects import Effect, parse_effects
from mi_lidar.core.errors import MiLidarError, SpecError
from mi_lidar.core.patterns import FiringPattern, get_pattern, is_pattern_file
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.dataset.spec import CameraSpec, DatasetSpec, LidarSpec
from mi_lidar.io.nuscenes import read_nuscenes_calibration
from mi_lidar.scene.camera import PinholeCamera

# OpenCV optical axes (x right, y down, z forward) expressed in a forward-looking body frame (x forward, y left, z up).
OPTICAL_TO_BODY = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
# Mitsuba's camera frame (x left, y up, z forward) from OpenCV's: both x and y flip.
MITSUBA_FROM_OPENCV = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass(frozen=True)
class RigCamera:
    """A mounted pinhole camera.

    Attributes:
        name: camera name. width, height: image size, pixels. fov_deg: horizontal field of view, deg.
        optical_to_ego: (4, 4) OpenCV optical frame to ego.
        principal_point: (cx, cy) pixels from the image's top-left corner, None for the image centre.
    """

    name: str
    width: int
    height: int
    fov_deg: float
    optical_to_ego: np.ndarray
    principal_point: tuple[float, float] | None = None

    def at(self, ego_to_world: np.ndarray) -> PinholeCamera:
        """The camera placed by the ego pose (4, 4)."""
        to_world = ego_to_world @ self.optical_to_ego @ MITSUBA_FROM_OPENCV
        return PinholeCamera(to_world, self.width, self.height, self.fov_deg, self.principal_point)

    @property
    def intrinsics(self) -> np.ndarray:
        """(3, 3) pixel intrinsics K."""
        return PinholeCamera(np.eye(4), self.width, self.height, self.fov_deg, self.principal_point).intrinsics


@dataclass(frozen=True)
class RigLidar:
    """A mounted Lidar: its spec, (4, 4) sensor-to-ego transform, sensor model and firing pattern."""

    spec: LidarSpec
    to_ego: np.ndarray
    model: SensorModel
    pattern: FiringPattern


@dataclass(frozen=True)
class Rig:
    """All sensors of a dataset's vehicle."""

    lidars: list[RigLidar]
    cameras: list[RigCamera]

    def calibration(self) -> dict:
        """KITTI calibration matrices: reference camera = ``cameras[0]``, velo = ``lidars[0]``.

        Returns:
            ``{"P2": (3, 4), "P3": ..., "R0_rect": (3, 3), "Tr_velo_to_cam": (3, 4), "Tr_imu_to_velo": (3, 4)}``
            with one ``P{i + 2}`` per camera (``K_i [R | t]`` from the reference camera's frame to
            camera i's pixels), ``P0 = P1 = P2`` (no grey cameras; present for loaders that expect
            them), and ``Tr_imu_to_velo`` the ego-to-Lidar transform (the ego frame plays KITTI's IMU).
        """
        reference = self.cameras[0]
        ego_to_reference = np.linalg.inv(reference.optical_to_ego)
        matrices = {}
        for i, camera in enumerate(self.cameras):
            reference_to_camera = np.linalg.inv(camera.optical_to_ego) @ reference.optical_to_ego
            matrices[f"P{i + 2}"] = camera.intrinsics @ reference_to_camera[:3, :]
        matrices = {"P0": matrices["P2"], "P1": matrices["P2"], **matrices}
        matrices["R0_rect"] = np.eye(3)
        matrices["Tr_velo_to_cam"] = (ego_to_reference @ self.lidars[0].to_ego)[:3, :]
        matrices["Tr_imu_to_velo"] = np.linalg.inv(self.lidars[0].to_ego)[:3, :]
        return matrices


def firing_pattern(spec: LidarSpec, resolve) -> FiringPattern:
    """The firing pattern of a rig Lidar.

    ``spec.pattern`` is a name of :data:`~mi_lidar.core.patterns.PATTERN_NAMES`, or a table or Ouster
    metadata file (``.csv``/``.npy``/``.json``) resolved by ``resolve(name) -> path`` (relative to the
    spec's folder).
    """
    text = spec.pattern
    return get_pattern(resolve(text) if is_pattern_file(text) else text)


def check_lidars(spec: DatasetSpec) -> list[str]:
    """What is wrong with the rig's patterns and sensor models, one ``"key: problem"`` line each (empty: nothing).

    The same builders the frames use, run once before any frame, so that a typo fails the run at once
    instead of failing every frame. The key is the entry at fault (``rig.lidars.0.density``), or the Lidar
    (``rig.lidars.0``) for limits that disagree (``max_range`` not above ``min_range``).
    """
    problems = []
    for i, lidar in enumerate(spec.rig.lidars):
        builders = {
            "pattern": partial(firing_pattern, lidar, spec.resolve),
            "effects": partial(parse_effects, lidar.effects),
            "density": partial(parse_density, lidar.density, resolve=spec.resolve),
        }
        parts = {}
        for key, build in builders.items():
            try:
                parts[key] = build()
            except MiLidarError as exc:
                problems.append(f"rig.lidars.{i}.{key}: {exc}")
        if len(parts) == len(builders):
            try:
                model_of(lidar, parts["effects"], parts["density"])
            except MiLidarError as exc:
                problems.append(f"rig.lidars.{i}: {exc}")
    return problems


def model_of(spec: LidarSpec, effects: list[Effect], density: ReturnDensity) -> SensorModel:
    """The sensor model of a rig Lidar from its built effects and return density."""
    return SensorModel(
        range_sigma=spec.range_sigma,
        min_range=spec.min_range,
        max_range=spec.max_range,
        max_segments=spec.max_segments,
        effects=effects,
        density=density,
    )


def sensor_model(spec: LidarSpec, resolve) -> SensorModel:
    """The sensor model of a rig Lidar (density files resolved by ``resolve(name) -> path``)."""
    return model_of(spec, parse_effects(spec.effects), parse_density(spec.density, resolve=resolve))


def camera_from_spec(spec: CameraSpec) -> RigCamera:
    """A rig camera from its spec (``xyz``/``rpy_deg`` mounts look along the mount's x axis)."""
    optical = spec.mount.to_matrix() if spec.mount.matrix is not None else spec.mount.to_matrix() @ OPTICAL_TO_BODY
    return RigCamera(spec.name, spec.width, spec.height, spec.fov_deg, optical)


def nuscenes_camera(name: str, camera: dict, scale: float) -> RigCamera:
    """A rig camera from a nuScenes calibration entry (``K``, ``width``, ``height``, ``cam2ego``), scaled by ``scale``.

    The field of view comes from the focal length ``K[0, 0]`` (nuScenes' pixels are square); the
    principal point is ``K``'s, moved from OpenCV's integer-centred pixel coordinates to the
    image-corner ones of :class:`~mi_lidar.scene.camera.PinholeCamera` (+0.5) and scaled with the image.
    """
    k = np.asarray(camera["K"], dtype=np.float64)
    fov = math.degrees(2 * math.atan(camera["width"] / (2 * k[0, 0])))
    width, height = round(camera["width"] * scale), round(camera["height"] * scale)
    centre = ((k[0, 2] + 0.5) * width / camera["width"], (k[1, 2] + 0.5) * height / camera["height"])
    return RigCamera(name, width, height, fov, camera["cam2ego"], centre)


def nuscenes_calibration(spec: DatasetSpec) -> dict | None:
    """The calibration of the rig's nuScenes file (:func:`~mi_lidar.io.nuscenes.read_nuscenes_calibration`), with
    every camera the spec names; None when the rig has no ``nuscenes`` entry.

    Raises:
        LogFormatError: the file is unreadable or not a nuScenes info pickle.
        SpecError: a camera the file does not hold.
    """
    nuscenes = spec.rig.nuscenes
    if nuscenes is None:
        return None
    calibration = read_nuscenes_calibration(spec.resolve(nuscenes.file))
    for name in nuscenes.cameras:
        if name not in calibration["cameras"]:
            raise SpecError(
                f"rig.nuscenes.cameras: {name!r} is not in {nuscenes.file}; "
                f"choose from {', '.join(sorted(calibration['cameras']))}"
            )
    return calibration


def check_nuscenes(spec: DatasetSpec) -> list[str]:
    """What is wrong with the rig's nuScenes file, as :func:`check_lidars` says it: read once before any frame (an
    unreadable pickle failed every frame, each retried, then the run)."""
    try:
        nuscenes_calibration(spec)
    except MiLidarError as exc:
        return [f"rig.nuscenes: {exc}"]
    return []


def build_rig(spec: DatasetSpec) -> Rig:
    """The rig of a dataset spec; nuScenes cameras follow the explicit ones and give the Lidars their mount.

    A Lidar whose mount is left at the default takes nuScenes' ``lidar2ego`` when a nuScenes file is given.
    """
    cameras = [camera_from_spec(c) for c in spec.rig.cameras]
    lidar_mounts = [s.mount.to_matrix() for s in spec.rig.lidars]
    nuscenes = spec.rig.nuscenes
    calibration = nuscenes_calibration(spec)
    if nuscenes is not None and calibration is not None:
        default_mount = LidarSpec().mount
        lidar_mounts = [
            calibration["lidar2ego"] if s.mount == default_mount else m for s, m in zip(spec.rig.lidars, lidar_mounts)
        ]
        for name in nuscenes.cameras:
            cameras.append(nuscenes_camera(name, calibration["cameras"][name], nuscenes.image_scale))
    lidars = [
        RigLidar(s, m, sensor_model(s, spec.resolve), firing_pattern(s, spec.resolve))
        for s, m in zip(spec.rig.lidars, lidar_mounts)
    ]
    return Rig(lidars, cameras)
