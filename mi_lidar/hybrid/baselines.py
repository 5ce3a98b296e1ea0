"""Baseline simulators of thesis 4.3.2.

* **Neighbour simulator** (log playback): for a query ray the logged hit points with
  perpendicular distance below ``d_perp`` are candidates and the one nearest along the ray is
  returned (its along-ray distance). Implemented by ray casting spheres of radius ``d_perp``
  around the logged points (Mitsuba ``ellipsoids`` with extent 1): the first sphere met is the
  candidate with the smallest along-ray distance, up to the sphere radius.
* **Mesh-primitive simulator**: opaque procedural meshes per class standing in for
  "open-source" models (trees: a trunk prism and an ellipsoidal crown surface; shrubs: an
  ellipsoid surface; rocks: a flattened ellipsoid), scaled to each annotated box, plus the
  ground mesh; p_hit = 1 everywhere and Gaussian range noise ``sigma``.
"""

from __future__ import annotations

import numpy as np
import trimesh

from .classes import CLASS_ID, class_id
from .model import EllipsoidSet, GroundMesh, HybridModel
from .primitives import rotation_z
from .trace import ellipsoid_scene, intersect
from .world import prism


class NeighborSimulator:
    """Log playback along each ray with a perpendicular-distance threshold.

    Args:
        points: (M, 3) logged world hit points, m.
        d_perp: perpendicular distance threshold, m.
    """

    def __init__(self, points: np.ndarray, d_perp: float = 0.3):
        self.points = np.asarray(points, float)
        n = len(self.points)
        self.scene = ellipsoid_scene(self.points, np.full((n, 3), d_perp), np.tile([0, 0, 0, 1.0], (n, 1)), 1.0)

    def simulate(self, origins: np.ndarray, directions: np.ndarray, min_range: float = 1.0,
                 max_range: float = 80.0) -> np.ndarray:
        """(N,) ranges (m, NaN = null) for (N, 3) world rays."""
        t, prim = intersect(self.scene, origins, directions)
        r = np.full(len(origins), np.nan)
        ok = prim >= 0
        r[ok] = np.sum((self.points[prim[ok]] - origins[ok]) * directions[ok], axis=1)
        r[(r < min_range) | (r > max_range)] = np.nan
        return r


def _class_mesh(label: int, extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (centred on the box centre, m) and faces of the stand-in mesh of a class."""
    lx, ly, lz = np.maximum(extents, 0.1)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    if label >= CLASS_ID["small_tree"]:
        crown_h = 0.6 * lz
        crown = sphere.vertices * [lx / 2, ly / 2, crown_h / 2] + [0, 0, lz / 2 - crown_h / 2]
        tv, tf = prism(np.array([0, 0, -lz / 2]), np.array([0, 0, lz / 2 - crown_h / 2]), 0.03 * lz, 0.02 * lz)
        return np.r_[crown, tv], np.r_[sphere.faces, tf + len(crown)]
    if label == CLASS_ID["rock"]:
        return sphere.vertices * [lx / 2, ly / 2, lz / 2], sphere.faces
    return sphere.vertices * [lx / 2, ly / 2, lz / 2], sphere.faces


def mesh_primitive_scene(objects: list[dict], ground: GroundMesh | None, sigma: float = 0.05) -> HybridModel:
    """Opaque-mesh baseline scene for annotation ``objects`` (see :mod:`.compose`), m and rad.

    Args:
        objects: annotation objects. ground: ground mesh (made opaque). sigma: range noise, m.

    Returns:
        A model with only triangles (p_hit = 1, range_sigma = ``sigma``).
    """
    parts = []
    if ground is not None and len(ground):
        parts.append(GroundMesh(ground.vertices, ground.faces, 1.0, sigma, ground.label))
    for i, obj in enumerate(objects):
        label = class_id(obj["class"])
        v, f = _class_mesh(label, np.asarray(obj["extents"], float))
        v = v @ rotation_z(float(obj["yaw"])).T + np.asarray(obj["center"], float)
        parts.append(GroundMesh(v, f, 1.0, sigma, label, i + 1))
    return HybridModel(GroundMesh.concat(parts), EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))))
