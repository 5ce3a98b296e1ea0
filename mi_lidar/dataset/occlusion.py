"""How much of each labelled object the reference camera sees: KITTI's ``occluded`` field.

For every box in front of the camera, a grid of camera rays through its 2D box is traced into the
scene. A ray whose first surface inside the 3D box's span belongs to the object *sees* it; a ray
that meets other surfaces first (another object, a building, the ground) and reaches the object
behind them is *hidden*; a ray that crosses the box without meeting the object (the gaps of a tree
canopy) counts for neither. The hidden fraction is ``hidden / (seen + hidden)``; KITTI's levels:

- 0: fully visible (less than :data:`PARTLY` hidden),
- 1: partly occluded (up to :data:`LARGELY`),
- 2: largely occluded (more than :data:`LARGELY` hidden, or no ray sees it),
- 3: unknown (no ray of the grid meets the object, e.g. a thin pole between grid rays).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.frames import scene_origin
from mi_lidar.core.scene_shapes import scene_ray_length
from mi_lidar.core.trace import mitsuba_ray
from mi_lidar.dataset.scenes import Box3D
from mi_lidar.hybrid.primitives import rotation_z
from mi_lidar.scene.camera import PinholeCamera

GRID = 16  # rays per side of a box's 2D box
MAX_LAYERS = 8  # surfaces a ray may pass before it reaches the object
STEP = 1e-3  # m: a continued ray starts this far past the surface it met
PARTLY, LARGELY = 0.1, 0.5  # hidden fractions of KITTI's levels 1 and 2
UNKNOWN = 3


def occlusion_level(hidden: float) -> int:
    """KITTI ``occluded`` level (0-3, see the module docstring) of a hidden fraction (NaN: unknown)."""
    if math.isnan(hidden):
        return UNKNOWN
    return 0 if hidden < PARTLY else 1 if hidden <= LARGELY else 2


def box_span(box: Box3D, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit distances (m) of rays from ``origin`` (3,) along unit ``directions`` (N, 3) through
    the box (slab test in the box frame); entry > exit where a ray misses it."""
    rotation = rotation_z(box.yaw)
    local_origin = rotation.T @ (origin - box.center)
    local = directions @ rotation  # rows: directions in the box frame
    with np.errstate(divide="ignore", invalid="ignore"):
        near = (-box.size / 2 - local_origin) / local
        far = (box.size / 2 - local_origin) / local
    near, far = np.nan_to_num(np.minimum(near, far), nan=-np.inf), np.nan_to_num(np.maximum(near, far), nan=np.inf)
    return np.maximum(near.max(axis=1), 0.0), far.min(axis=1)


def hidden_fractions(
    scene, camera: PinholeCamera, boxes: list[Box3D], instance_of_shape: np.ndarray
) -> dict[int, float]:
    """Hidden fraction (0-1, NaN when unknown) of every box the camera sees part of, by instance id.

    Args:
        scene: the Mitsuba scene. camera: the reference camera placed in the world.
        boxes: labelled objects (boxes reaching behind the camera or outside the image are left out).
        instance_of_shape: instance id per Dr.Jit registry id of the scene's shapes (0: stuff).
    """
    origin = camera.to_world[:3, 3]
    to_world = np.linalg.inv(camera.world_to_opencv)[:3, :3]
    inverse_k = np.linalg.inv(camera.intrinsics)
    steps = (np.arange(GRID) + 0.5) / GRID
    directions, owner, exit_, kept = [], [], [], []
    for box in boxes:
        uv, depth, _ = camera.project(box.corners())
        if np.any(depth <= 0.1):
            continue
        low = np.clip(uv.min(0), 0, [camera.width, camera.height])
        high = np.clip(uv.max(0), 0, [camera.width, camera.height])
        if np.any(high - low <= 0):
            continue
        u, v = np.meshgrid(low[0] + steps * (high[0] - low[0]), low[1] + steps * (high[1] - low[1]))
        rays = np.c_[u.ravel(), v.ravel(), np.ones(u.size)] @ inverse_k.T @ to_world.T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        near, far = box_span(box, origin, rays)
        crossing = far > near
        directions.append(rays[crossing])
        owner.append(np.full(crossing.sum(), box.instance))
        exit_.append(far[crossing])
        kept.append(box.instance)
    if not kept:
        return {}
    verdict = _trace(scene, origin, *(np.concatenate(a) for a in (directions, owner, exit_)), instance_of_shape)
    owner = np.concatenate(owner)
    fractions = {}
    for instance in kept:
        seen = np.count_nonzero((owner == instance) & (verdict == 1))
        hidden = np.count_nonzero((owner == instance) & (verdict == 2))
        fractions[instance] = hidden / (seen + hidden) if seen + hidden else math.nan
    return fractions


def _trace(scene, origin, directions, owner, exit_, instance_of_shape) -> np.ndarray:
    """Per ray: 1 sees its object first, 2 meets it behind other surfaces, 0 crosses its box without meeting it."""
    origin = origin - scene_origin(scene)  # a georeferenced scene is loaded at a local origin
    length = scene_ray_length(scene)  # Mitsuba's distances are in units of it
    verdict = np.zeros(len(directions), np.uint8)
    start = np.zeros(len(directions))
    blocked = np.zeros(len(directions), bool)
    open_ = np.ones(len(directions), bool)
    for _ in range(MAX_LAYERS):
        index = np.flatnonzero(open_)
        if not len(index):
            break
        d = directions[index]
        ray = mitsuba_ray(mi.Point3f(*(origin + d * start[index, None]).T), mi.Vector3f(*d.T), length)
        si = scene.ray_intersect(ray, mi.RayFlags.Minimal, True)
        valid = np.asarray(si.is_valid())
        distance = start[index] + np.where(valid, np.asarray(si.t) * length, np.inf)
        shape = np.asarray(dr.reinterpret_array(mi.UInt32, si.shape)).astype(np.int64)
        instance = instance_of_shape[np.where(valid, shape, 0)]  # registry id 0: no shape
        inside = distance <= exit_[index]
        own = inside & (instance == owner[index])
        verdict[index[own]] = np.where(blocked[index[own]], 2, 1)
        other = inside & ~own
        blocked[index[other]] = True
        start[index[other]] = distance[other] + STEP
        open_[index[~other]] = False
    return verdict
