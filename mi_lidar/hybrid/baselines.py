"""Baseline simulators of thesis 4.3.2.

* **Neighbour simulator** (log playback): for a query ray the logged hit points with
  perpendicular distance below ``d_perp`` are candidates and the one nearest along the ray is
  returned (its along-ray distance). Implemented by ray casting spheres of radius ``d_perp``
  around the logged points (Mitsuba ``ellipsoids`` with extent 1): the first sphere met is the
  candidate with the smallest along-ray distance, up to the sphere radius.
* **Mesh-model simulator** (the thesis's baseline): per annotated object, the stock mesh model
  of its class with the closest box extents (:mod:`.mesh_models`), placed at the object's pose
  without rescaling, plus the ground mesh; every triangle opaque (p_hit = 1) with Gaussian range
  noise ``sigma``.
* **Box-surface simulator** (a more generous variant, not in the thesis): per annotated object a
  smooth closed surface scaled to its box (trees: a trunk prism under an ellipsoidal crown
  surface over the top 60 % of the box height; shrubs and rocks: the ellipsoid surface
  inscribed in the box), centred on the object's centre and turned by its yaw, plus the ground;
  opaque, Gaussian range noise ``sigma``.
"""

from __future__ import annotations

import numpy as np
import trimesh

from mi_lidar.hybrid.classes import CLASS_ID, class_id
from mi_lidar.hybrid.mesh_models import MeshModelLibrary
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh, HybridModel
from mi_lidar.hybrid.primitives import rotation_z
from mi_lidar.hybrid.trace import ellipsoid_scene, intersect
from mi_lidar.hybrid.world import prism


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

    def simulate(
        self, origins: np.ndarray, directions: np.ndarray, min_range: float = 1.0, max_range: float = 80.0
    ) -> np.ndarray:
        """(N,) ranges (m, NaN = null) for (N, 3) world rays."""
        t, prim = intersect(self.scene, origins, directions)
        r = np.full(len(origins), np.nan)
        ok = prim >= 0
        r[ok] = np.sum((self.points[prim[ok]] - origins[ok]) * directions[ok], axis=1)
        r[(r < min_range) | (r > max_range)] = np.nan
        return r


def _box_surface(label: int, extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (centred on the origin, m) and faces of the closed surface scaled to box ``extents`` (3,) m."""
    lx, ly, lz = np.maximum(extents, 0.1)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    if label >= CLASS_ID["small_tree"]:
        crown_h = 0.6 * lz
        crown = sphere.vertices * [lx / 2, ly / 2, crown_h / 2] + [0, 0, lz / 2 - crown_h / 2]
        tv, tf = prism(np.array([0, 0, -lz / 2]), np.array([0, 0, lz / 2 - crown_h / 2]), 0.03 * lz, 0.02 * lz)
        return np.r_[crown, tv], np.r_[sphere.faces, tf + len(crown)]
    return sphere.vertices * [lx / 2, ly / 2, lz / 2], sphere.faces


def _opaque_scene(
    ground: GroundMesh | None, objects: list[tuple[np.ndarray, np.ndarray, int]], sigma: float
) -> HybridModel:
    """A model of opaque triangles (p_hit = 1, range sigma ``sigma`` m): the ground and per object
    (world vertices (V, 3) m, faces (F, 3), class id); object ``i`` gets instance ``i + 1``."""
    parts = []
    if ground is not None and len(ground):
        parts.append(GroundMesh(ground.vertices, ground.faces, 1.0, sigma, ground.label))
    for i, (vertices, faces, label) in enumerate(objects):
        parts.append(GroundMesh(vertices, faces, 1.0, sigma, label, i + 1))
    return HybridModel(GroundMesh.concat(parts), EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))))


def mesh_model_scene(
    objects: list[dict], ground: GroundMesh | None, library: MeshModelLibrary, sigma: float = 0.05
) -> HybridModel:
    """The thesis's mesh-model baseline scene for annotation ``objects`` (see :mod:`.compose`).

    Args:
        objects: annotation objects (class, center m, yaw rad, extents m).
        ground: ground mesh (made opaque); None for none.
        library: stock models; each object gets the model of its class with the closest box.
        sigma: Gaussian range noise, m.

    Returns:
        A model with only triangles (p_hit = 1, range_sigma = ``sigma``); ``info["models"]``
        lists the chosen model id per object.
    """
    chosen = [library.best_match(obj["class"], obj["extents"]) for obj in objects]
    meshes = [(m.placed(float(obj["yaw"]), obj["center"]), m.faces, m.label) for m, obj in zip(chosen, objects)]
    model = _opaque_scene(ground, meshes, sigma)
    model.info["models"] = [m.id for m in chosen]
    return model


def box_surface_scene(objects: list[dict], ground: GroundMesh | None, sigma: float = 0.05) -> HybridModel:
    """The box-surface baseline scene: a closed surface scaled to each annotated box, at its pose.

    Args:
        objects: annotation objects (class, center m, yaw rad, extents m).
        ground: ground mesh (made opaque); None for none.
        sigma: Gaussian range noise, m.

    Returns:
        A model with only triangles (p_hit = 1, range_sigma = ``sigma``).
    """
    meshes = []
    for obj in objects:
        label = class_id(obj["class"])
        vertices, faces = _box_surface(label, np.asarray(obj["extents"], float))
        meshes.append((vertices @ rotation_z(float(obj["yaw"])).T + np.asarray(obj["center"], float), faces, label))
    return _opaque_scene(ground, meshes, sigma)
