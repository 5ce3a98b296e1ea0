"""Ray casting with Mitsuba on plain shapes built from numpy arrays (no mi-lidar plugins).

Two scene kinds are used: a triangle mesh and an analytic ``ellipsoids`` set, by the synthetic
world's own sensor (:mod:`.world`) and the baselines (:mod:`.baselines`), which are independent of
the product's simulation core on purpose. Elements of product scenes are traced by the core's one
tracer (:func:`mi_lidar.core.trace.trace_rounds`). The one thing shared with it is the length of the
ray directions handed to Mitsuba (:func:`mi_lidar.core.elements.scene_ray_length`), without which
Mitsuba's ellipsoid test misses small elements far away.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from mi_lidar.core.scene_shapes import scene_ray_length
from mi_lidar.core.trace import mitsuba_ray


def mesh_scene(vertices: np.ndarray, faces: np.ndarray):
    """A Mitsuba scene holding one triangle mesh.

    Args:
        vertices: (V, 3) positions, m.
        faces: (F, 3) vertex indices.
    """
    mesh = mi.Mesh("mesh", len(vertices), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(vertices, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).ravel())
    params.update()
    return mi.load_dict({"type": "scene", "mesh": mesh})


def ellipsoid_scene(centers: np.ndarray, scales: np.ndarray, quaternions: np.ndarray, extent: float):
    """A Mitsuba scene holding one analytic ellipsoid set.

    Args:
        centers: (N, 3) m. scales: (N, 3) standard deviations, m. quaternions: (N, 4) (x, y, z, w).
        extent: drawn Mahalanobis radius, in sigmas.
    """
    as_tensor = lambda a: mi.TensorXf(np.ascontiguousarray(a, np.float32))
    return mi.load_dict(
        {
            "type": "scene",
            "ellipsoids": {
                "type": "ellipsoids",
                "centers": as_tensor(centers),
                "scales": as_tensor(scales),
                "quaternions": as_tensor(quaternions),
                "extent": float(extent),
            },
        }
    )


def intersect(scene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of rays with ``scene``.

    Args:
        origins, directions: (N, 3) world-frame rays (directions unit), m.

    Returns:
        ``t`` (N,) float64 distance along the ray, m (inf for a miss) and ``prim`` (N,) int64
        primitive index (-1 for a miss).
    """
    length = scene_ray_length(scene)  # Mitsuba's distances are in units of it
    o = mi.Point3f(np.ascontiguousarray(np.asarray(origins, np.float32).T))
    d = mi.Vector3f(np.ascontiguousarray(np.asarray(directions, np.float32).T))
    si = scene.ray_intersect(mitsuba_ray(o, d, length), mi.RayFlags.Minimal, True)
    valid = np.array(si.is_valid(), bool)
    t = np.where(valid, np.array(si.t, np.float64) * length, np.inf)
    prim = np.where(valid, np.array(si.prim_index, np.int64), -1)
    return t, prim
