"""Mitsuba's analytic ``cylinder`` is loaded as a triangle mesh (a workaround for Mitsuba 3.9.1's cylinder test).

Mitsuba 3.9.1's ``cylinder`` (``src/shapes/cylinder.cpp``, ``ray_intersect_preliminary_impl``) maps the ray
into the unit cylinder's frame and solves ``A t^2 + B t + C = 0`` there from the ray's origin, in float32 in
the ``llvm_ad`` and ``cuda`` variants::

    C = dr::square(ox) + dr::square(oy) - dr::square(radius);

The origin lies about ``D / radius`` units from the axis (``D`` its distance, m), so ``C`` and ``B^2`` are
of order ``(D / radius)^2`` while the discriminant ``B^2 - 4 A C`` that decides the hit is at most ``4 A``:
float32 keeps ``eps (D / radius)^2`` of it. (Mitsuba's ``sphere`` first moves the origin next to the
centre; the cylinder does not.) The direction's length changes nothing, the discriminant being homogeneous
in it; only a start near the cylinder does (2 m before a 2 cm pole 250 m away: within 0.1 mm). Of the rays
aimed inside a 5 cm pole, 0.2 % were missed at 60 m, 8 % at 120 m and 60 % at 250 m, and the ranges of 30 %
were off by more than 1 mm at 30 m (by up to 8 cm at 250 m; ``tests/test_cylinder_precision.py``,
``docs/architecture.md``).

Embree's triangle test has no such cancellation, so :func:`mi_lidar.load_scene` hands Mitsuba every
``cylinder`` as the mesh :func:`cylinder_mesh` builds (:func:`mesh_cylinders` renames the parsed shapes to
:data:`PLUGIN` before they are made): the same open tube (Mitsuba's cylinder has no end caps), its vertices
on Mitsuba's surface (the cylinder's own ``to_world``, which folds in ``p0``, ``p1`` and ``radius``), each
facet within :data:`SAGITTA` of it and the facet's normal within :data:`MAX_NORMAL_ERROR` of the surface's,
Mitsuba's texture coordinates, and every other property of the shape (id, BSDF such as a ``lidar_material``,
``flip_normals``, an emitter). Vertex normals keep camera renders smooth; Lidar rays use the facet's
normal. A cylinder is then ``2 n`` triangle elements, like a ``cube``'s 12. Now no ray aimed inside a 2-10
cm pole is missed to 250 m and ranges are within 0.2 mm, except for the rays (up to 1 in 20,000) that
slip between two facets (Embree's default triangle test is not watertight) and meet the inside of the far
wall. Near the sensor the analytic cylinder was exact; its normals are now off by up to 2 degrees (the
regression scans of the bundled ``indoor_planar`` targets moved by at most 0.2 mm and 0.02 in the cosine of
incidence). A cylinder costs about 3 ms at load; scenes without one load as before. Drop this module when
``test_analytic_cylinders_still_miss_in_this_mitsuba`` fails: Mitsuba's test is then exact.
"""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import SceneError

PLUGIN = "mi_lidar_cylinder_mesh"  # the shape plugin a parsed ``cylinder`` is renamed to
SAGITTA = 1e-4  # m: the farthest a facet lies from the cylinder
MAX_NORMAL_ERROR = 2.0  # degrees: the largest angle between a facet's normal and the cylinder's
GEOMETRY = ("p0", "p1", "radius", "to_world")  # the properties that place Mitsuba's cylinder


def facet_count(radius: float) -> int:
    """Facets around a cylinder of ``radius`` (m), its vertices on the circle: enough that each facet lies
    within :data:`SAGITTA` of the circle (a facet spans ``2 pi / n``: its sagitta is ``radius (1 - cos(pi / n))``)
    and its normal within :data:`MAX_NORMAL_ERROR` of the circle's (at most ``180 / n`` degrees)."""
    for_sagitta = math.pi / math.acos(max(1.0 - SAGITTA / radius, -1.0)) if radius > 0 else 1.0
    return max(math.ceil(for_sagitta), math.ceil(180.0 / MAX_NORMAL_ERROR))


def cylinder_mesh(props: mi.Properties) -> mi.Mesh:
    """The triangle mesh of the ``cylinder`` with properties ``props`` (the constructor of :data:`PLUGIN`).

    Mitsuba's own cylinder is made from the properties that are not objects (it checks them as for any
    cylinder) for its ``to_world`` ``M``, which maps the unit tube (radius 1, ``z`` from 0 to 1) to the
    world. The mesh has ``n + 1`` vertices on each end circle (the seam is doubled for Mitsuba's texture
    coordinates ``(phi / 2 pi, z)``), ``n = facet_count(radius)`` for the larger radius of ``M``, and every
    property but the placing ones (:data:`GEOMETRY`).

    Raises:
        SceneError: the cylinder has no radius or no length; or an object nested in it that no shape takes
            (e.g. a sampler), named.
    """
    values = {name: props[name] for name in props.keys()}
    objects = {name for name, value in values.items() if isinstance(value, mi.Object)}  # BSDF, emitter ...
    settings = {name: value for name, value in values.items() if name not in objects}
    cylinder = mi.load_dict({"type": "cylinder", **settings})  # Mitsuba's own, which checks the settings
    matrix = np.asarray(mi.traverse(cylinder)["to_world"].matrix, np.float64).reshape(4, 4)
    linear, offset = matrix[:3, :3], matrix[:3, 3]
    radius, length = (
        float(max(np.linalg.norm(linear[:, 0]), np.linalg.norm(linear[:, 1]))),
        float(np.linalg.norm(linear[:, 2])),
    )
    if not (radius > 0 and length > 0):  # NaN too (p0 = p1)
        raise SceneError(
            f"cylinder {props.id()!r}: radius {radius:g} m, length {length:g} m (from its p0, p1, radius and "
            "to_world); give a radius > 0 and p1 away from p0"
        )
    n = facet_count(radius)
    phi = 2.0 * np.pi * (np.arange(n + 1) % n) / n  # the last column is the first again (the seam)
    ring = np.c_[np.cos(phi), np.sin(phi)]
    local = np.r_[np.c_[ring, np.zeros(n + 1)], np.c_[ring, np.ones(n + 1)]]
    tangent = np.c_[-ring[:, 1], ring[:, 0], np.zeros(n + 1)] @ linear.T
    normal = np.cross(tangent, linear[:, 2])  # Mitsuba's: cross(dp/du, dp/dv)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    u = np.arange(n + 1) / n
    k = np.arange(n)
    top = k + n + 1
    faces = np.r_[np.c_[k, k + 1, top + 1], np.c_[k, top + 1, top]]  # outward: cross(edge around, edge up)

    rest = mi.Properties()
    for name, value in values.items():
        if name not in GEOMETRY:
            rest[name] = value
    rest.set_id(props.id())
    mesh = mi.Mesh(props.id(), 2 * (n + 1), 2 * n, rest, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float((local @ linear.T + offset).astype(np.float32).ravel())
    params["vertex_normals"] = mi.Float(np.r_[normal, normal].astype(np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(np.c_[np.r_[u, u], local[:, 2]].astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    if rest.unqueried():  # objects a shape does not take: Mitsuba's cylinder would refuse them too
        unused = ", ".join(f"{type(values[name]).__name__} ({name!r})" for name in rest.unqueried())
        raise SceneError(f"cylinder {props.id()!r}: a shape takes no {unused}; remove it from the shape")
    return mesh


def mesh_cylinders(state) -> None:
    """Rename the ``cylinder`` shapes of a parsed scene (``mi.parser.ParserState``) to :data:`PLUGIN`, in place,
    so that instantiating the state makes them meshes (:func:`cylinder_mesh`); registers the plugin for the
    active variant when there are any."""
    nodes = [node for node in state.nodes if node.props.plugin_name() == "cylinder"]
    if nodes:
        mi.register_shape(PLUGIN, cylinder_mesh)
    for node in nodes:
        node.props.set_plugin_name(PLUGIN)
