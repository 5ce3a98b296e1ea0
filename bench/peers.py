"""The peers the core benchmark compares with, on the same rays (see :mod:`bench.bench_core`).

* :func:`raw_pass_through`: the minimal pass-through loop written directly on Mitsuba, the
  reference of the sampler (what it costs before any sensor model);
* Open3D's ``RaycastingScene`` (first hits, and a numpy pass-through loop over ellipsoids drawn as
  icosahedra);
* embreex (Embree's Python binding, first hits on one thread).

A peer that is not installed is reported by :func:`missing_peer`, never by a crash.
"""

from __future__ import annotations

import importlib

import numpy as np


# ----------------------------------------------------------------------------- raw Mitsuba
def raw_pass_through(scene, p_hit: dict, origin, direction, ray_id, max_range: float, max_segments: int):
    """The minimal pass-through loop written directly on Mitsuba: first-return range per ray (NaN = miss).

    One symbolic loop: a coherent preliminary intersection from where the ray continues, the
    element's hit probability from a flat array (shape offset + primitive index), one
    counter-based uniform number per element (TEA of ray id and element index), the element's
    nominal range as the result where the beam returns, a restart 1e-4 m past the element where it
    passes; at most ``max_segments`` elements and nothing beyond ``max_range`` (m).

    Args:
        scene: the Mitsuba scene.
        p_hit: shape id -> (primitive count,) hit probabilities.
        origin, direction: the rays (``mi.Point3f``, ``mi.Vector3f``, unit directions).
        ray_id: (N,) ``mi.UInt32`` keys of the random numbers.
    """
    import drjit as dr
    import mitsuba as mi

    shapes = scene.shapes()
    registry = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0]) for shape in shapes]
    offset = np.zeros(max(registry) + 1, np.uint32)
    flat, start = [], 0
    for shape, rid in zip(shapes, registry):
        offset[rid] = start
        flat.append(np.asarray(p_hit[shape.id()], np.float32))
        start += len(flat[-1])
    offsets, probabilities = mi.UInt32(offset), mi.Float(np.concatenate(flat))
    n = dr.width(ray_id)

    def going(k, alive, start, z):
        return alive

    def meet_element(k, alive, start, z):
        ray = mi.Ray3f(start, direction)
        pi = scene.ray_intersect_preliminary(ray, True, alive)
        point = ray(pi.t)
        nominal = dr.dot(point - origin, direction)
        valid = pi.is_valid() & (nominal <= max_range)
        element = dr.gather(mi.UInt32, offsets, dr.reinterpret_array(mi.UInt32, pi.shape), valid) + pi.prim_index
        p = dr.gather(mi.Float, probabilities, element, valid)
        u = mi.sample_tea_float32(ray_id, dr.opaque(mi.UInt32, 0x2545F491) + k * 0x85EBCA77, 8)
        returned = valid & (u < p)
        k = k + 1
        restart = mi.Point3f(point + 1e-4 * direction)
        return k, valid & ~returned & (k < max_segments), restart, dr.select(returned, nominal, z)

    state = (dr.zeros(mi.UInt32, n), dr.full(mi.Bool, True, n), mi.Point3f(origin), dr.full(mi.Float, dr.nan, n))
    return dr.while_loop(state, going, meet_element, label="raw pass-through")[3]


# ----------------------------------------------------------------------------------- Open3D
def open3d_scene(vertices: np.ndarray, faces: np.ndarray, veg: dict[str, np.ndarray] | None, extent: float):
    """Open3D scene of a mesh (geometry 0) and, given ``veg``, its ellipsoids as icosahedra (geometry 1).

    Args:
        vertices, faces: (V, 3) vertices (m) and (F, 3) faces of the mesh.
        veg: ``centers`` (N, 3), ``scales`` (N, 3) sigmas and ``quaternions`` (N, 4) (x, y, z, w) of
            the ellipsoids, or None.
        extent: the ellipsoids' surface, in sigmas (the icosahedra's radius).

    Returns:
        ``(scene, faces_per_ellipsoid)``; 0 faces without ``veg``.
    """
    o3d = import_open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    faces_per_ellipsoid = 0
    if veg is not None:
        ico = o3d.geometry.TriangleMesh.create_icosahedron(radius=1.0)
        unit = np.asarray(ico.vertices)
        tri = np.asarray(ico.triangles)
        faces_per_ellipsoid = len(tri)
        q = veg["quaternions"]
        rot = _quaternion_matrices(q)
        local = unit[None] * (veg["scales"][:, None, :] * extent)
        world = np.einsum("nij,nvj->nvi", rot, local) + veg["centers"][:, None, :]
        all_faces = tri[None] + (np.arange(len(q)) * len(unit))[:, None, None]
        scene.add_triangles(
            o3d.core.Tensor(world.reshape(-1, 3).astype(np.float32)),
            o3d.core.Tensor(all_faces.reshape(-1, 3).astype(np.uint32)),
        )
    return scene, faces_per_ellipsoid


def import_open3d():
    """Import Open3D, explaining the usual failure (its wheel links the system's libusb)."""
    try:
        import open3d
    except ImportError as exc:
        hint = " Install it with `apt-get install libusb-1.0-0`." if "libusb" in str(exc) else ""
        raise RuntimeError(f"the benchmark compares with Open3D, which does not import: {exc}.{hint}") from exc
    return open3d


def missing_peer(module: str) -> str:
    """Why peer ``module`` cannot run here ("" when it imports), with what to type."""
    try:
        importlib.import_module(module)
    except ImportError as exc:
        fix = "apt-get install libusb-1.0-0" if "libusb" in str(exc) else f"pip install {module}"
        return f"{module} does not import ({exc}); `{fix}` or `make bench` installs it"
    return ""


def _quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of unit quaternions (x, y, z, w)."""
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def open3d_first_hit(scene, origin: np.ndarray, direction: np.ndarray, threads: int) -> dict:
    """Open3D first hits of rays ``(origin, direction)`` on ``threads`` threads."""
    o3d = import_open3d()
    rays = o3d.core.Tensor(np.concatenate([origin, direction], axis=1).astype(np.float32))
    return scene.cast_rays(rays, nthreads=threads)


def open3d_pass_through(
    scene,
    faces_per_ellipsoid: int,
    p_hit: np.ndarray,
    origin: np.ndarray,
    direction: np.ndarray,
    rng: np.random.Generator,
    threads: int,
    max_range: float,
    max_segments: int,
) -> np.ndarray:
    """The pass-through sampling loop on Open3D: first-return range per ray (NaN = miss).

    The mesh (geometry 0) is opaque; an icosahedron's entry face returns with its ellipsoid's
    ``p_hit``, its exit face is crossed without a draw. Rays stop after ``max_segments`` elements
    or beyond ``max_range`` (m).
    """
    n = len(origin)
    result = np.full(n, np.nan, np.float32)
    segments = np.zeros(n, np.int32)
    live = np.arange(n)
    start = origin.copy()
    while live.size:
        hits = open3d_first_hit(scene, start[live], direction[live], threads)
        t = hits["t_hit"].numpy()
        geometry = hits["geometry_ids"].numpy()
        prim = hits["primitive_ids"].numpy()
        normal = hits["primitive_normals"].numpy()
        point = start[live] + t[:, None] * direction[live]
        nominal = np.einsum("ij,ij->i", point - origin[live], direction[live])
        valid = np.isfinite(t) & (nominal <= max_range)
        is_veg = valid & (geometry == 1)
        exit_face = is_veg & (np.einsum("ij,ij->i", normal, direction[live]) > 0)
        element = valid & ~exit_face
        p = np.where(is_veg, p_hit[np.where(is_veg, prim // faces_per_ellipsoid, 0)], 1.0)
        returned = element & (rng.random(live.size) < p)
        result[live[returned]] = nominal[returned]
        segments[live] += element
        keep = valid & ~returned & (segments[live] < max_segments)
        start[live] = point + 1e-4 * direction[live]
        live = live[keep]
    return result


# ---------------------------------------------------------------------------------- embreex
def embreex_first_hit(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, direction: np.ndarray):
    """A callable casting the rays on a mesh with embreex (first hit, one thread), or None when not installed."""
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        return None
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, vertices[faces].astype(np.float32))
    return lambda: scene.run(origin, direction, output=1)
