"""Ray casting with Mitsuba on plain shapes built from numpy arrays (no mi-lidar plugins).

Two scene kinds are used: a triangle mesh and an analytic ``ellipsoids`` set. Multi-element
traversal restarts each ray just past the element it met (``1e-4`` m), which for ellipsoids
skips the exit surface of the one entered (GUIDE section 5), so each step yields the next entry.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np

RESTART_EPS = 1e-4  # m, offset of a restarted ray past the element it met


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
    o = mi.Point3f(np.ascontiguousarray(np.asarray(origins, np.float32).T))
    d = mi.Vector3f(np.ascontiguousarray(np.asarray(directions, np.float32).T))
    si = scene.ray_intersect(mi.Ray3f(o, d), mi.RayFlags.Minimal, True)
    valid = np.array(si.is_valid(), bool)
    t = np.where(valid, np.array(si.t, np.float64), np.inf)
    prim = np.where(valid, np.array(si.prim_index, np.int64), -1)
    return t, prim


def trace_elements(
    scene, origins: np.ndarray, directions: np.ndarray, max_range: np.ndarray | float, max_elements: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """All elements met along each ray up to ``max_range``, in order.

    Args:
        scene: mesh or ellipsoid scene.
        origins, directions: (N, 3) rays, m.
        max_range: (N,) or scalar, m; elements entered beyond it are not reported.
        max_elements: K, the most elements reported per ray.

    Returns:
        ``ids`` (N, K) int64 element indices (-1 = none) and ``t`` (N, K) entry ranges, m (inf = none).
    """
    n = len(origins)
    origins = np.asarray(origins, np.float64)
    directions = np.asarray(directions, np.float64)
    limit = np.broadcast_to(np.asarray(max_range, np.float64), (n,))
    ids = np.full((n, max_elements), -1, np.int64)
    ts = np.full((n, max_elements), np.inf)
    alive = np.arange(n)
    offset = np.zeros(n)
    for k in range(max_elements):
        if len(alive) == 0:
            break
        start = origins[alive] + directions[alive] * offset[alive, None]
        t, prim = intersect(scene, start, directions[alive])
        total = offset[alive] + t
        found = np.isfinite(t) & (total <= limit[alive])
        ids[alive[found], k] = prim[found]
        ts[alive[found], k] = total[found]
        offset[alive] = total + RESTART_EPS
        alive = alive[found]
    return ids, ts
