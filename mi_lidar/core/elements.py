"""The element table: per-element Lidar properties and geometry of a loaded Mitsuba scene, in flat arrays.

Every triangle and every ellipsoid of the scene is an *element* with a global index. Shapes are
taken in :func:`ordered_shapes` order; for each shape the table records where its elements start,
so an intersection ``(si.shape, si.prim_index)`` maps to the global index
``element_offset[registry_id(si.shape)] + si.prim_index`` and per-element values are single gathers
from flat arrays. Calibration replaces those arrays (for example ``p_hit`` by the sigmoid of a
differentiable logit array, or ``vertex_positions`` by fitted heights) and gradients flow through
the same gathers.

Values come, in order of precedence, from per-element attributes (mesh PLY face properties
``p_hit_0``, ``range_sigma_0``, ``label_0``, ``reflectivity_0``; ellipsoid PLY extras or ``(N, 1)``
tensors ``p_hit``, ``range_sigma``, ``label``, ``reflectivity``), from the shape's nested
``lidar_material``, and from defaults (opaque, the sensor's ``range_sigma``, label 0, reflectivity
:data:`DEFAULT_REFLECTIVITY`).

Two ways to build the :class:`~mi_lidar.core.segment.Segment` of an element met by a ray:

* :meth:`ElementTable.traced_segment` from a Mitsuba intersection (the sampler: no gradients);
* :meth:`ElementTable.segment` from the table's own geometry along any ray (the likelihood):
  triangles from their vertices, ellipsoids from their parameters, other shapes (analytic spheres,
  disks, rectangles) from the tangent plane at the traced point. It is differentiable in the
  geometry arrays and in the ray, so fitting heights, ellipsoids, beam angles or extrinsics works.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import SceneError
from mi_lidar.core.fitting import lookup
from mi_lidar.core.scene_shapes import (
    ELLIPSOID_STRIDE,
    check_element_values,
    check_ellipsoids,
    element_attribute,
    ellipsoid_sizes,
    is_ellipsoids,
    lidar_material,
    ordered_shapes,
    registry_id,
)
from mi_lidar.core.segment import (
    DEFAULT_REFLECTIVITY,
    ELLIPSOID,
    SURFACE,
    ElementValues,
    Segment,
    corners,
    element_segment,
    ray_closest_approach,
    ray_restricted_gaussian,
    rotate_inverse,
)
from mi_lidar.core.trace import mitsuba_ray_length


@dataclass
class ElementTable:
    """Flat per-element arrays of a scene (see the module docstring).

    Attributes:
        shape_ids: Mitsuba ids of the shapes, in table order.
        shape_kinds: ``"mesh"`` (triangles with editable vertices), ``"ellipsoids"`` or ``"surface"``
            (an analytic shape) per shape.
        element_counts: elements per shape.
        element_offset: per registry id, index of the shape's first element.
        shape_index: per registry id, index of the shape in ``shape_ids``.
        p_hit, range_sigma: per-element hit probability and range sigma (m); NaN sigma = sensor default.
        label: per-element class label.
        reflectivity: per-element Lambertian reflectivity at the sensor's wavelength (1 = white
            diffuse target, above 1 for retroreflectors).
        kind: per-element ``SURFACE`` or ``ELLIPSOID``.
        element_shape: per element, index of its shape in ``shape_ids``.
        ellipsoid_data: all ellipsoids' (center, scale, quaternion), 10 floats each.
        ellipsoid_extent: per ellipsoid, extent in sigmas.
        ellipsoid_index: per element, index into the ellipsoid arrays (0 for surfaces).
        vertex_positions: all meshes' vertices, flat (3 V) floats, m.
        face_vertices: per element, 3 global vertex indices, flat (3 n_elements) (0 for non-triangles).
        is_triangle: per element, True for triangles of meshes with editable vertices.
        vertex_offset: per shape, index of its first vertex in ``vertex_positions`` (-1 if not a mesh).
        vertex_counts: per shape, vertex count (0 if not a mesh).
        ray_length: length of the ray directions handed to Mitsuba, m
            (:func:`~mi_lidar.core.trace.mitsuba_ray_length`: 1 without ellipsoids).
        smoothing: > 0 while fitting ellipsoid geometry: ellipsoids return with the soft silhouette
            of :mod:`~mi_lidar.core.smoothing` (sigmas of the element); 0 is the exact model.
    """

    shape_ids: list
    shape_kinds: list
    element_counts: list
    element_offset: mi.UInt32
    shape_index: mi.UInt32
    p_hit: mi.Float
    range_sigma: mi.Float
    label: mi.UInt32
    reflectivity: mi.Float
    kind: mi.UInt32
    element_shape: mi.UInt32
    ellipsoid_data: mi.Float
    ellipsoid_extent: mi.Float
    ellipsoid_index: mi.UInt32
    vertex_positions: mi.Float
    face_vertices: mi.UInt32
    is_triangle: mi.Bool
    vertex_offset: list
    vertex_counts: list
    ray_length: float = 1.0
    smoothing: float = 0.0

    @property
    def has_triangles(self) -> bool:
        """True when a shape is a triangle mesh (its segments then know their corners)."""
        return "mesh" in self.shape_kinds

    @property
    def n_elements(self) -> int:
        return int(sum(self.element_counts))

    @property
    def has_ellipsoids(self) -> bool:
        """Whether any element is an ellipsoid."""
        return "ellipsoids" in self.shape_kinds

    @classmethod
    def from_scene(cls, scene) -> ElementTable:
        """Build the table of a loaded scene; raise :class:`SceneError` on invalid values."""
        shapes = ordered_shapes(scene)
        if not shapes:
            raise SceneError("the scene has no shapes; add a mesh or an ellipsoid set")
        n_registry = max(registry_id(s) for s in shapes) + 1
        element_offset = np.zeros(n_registry, np.uint32)
        shape_index = np.zeros(n_registry, np.uint32)
        columns: dict[str, list] = {
            k: [] for k in ("p_hit", "range_sigma", "label", "reflectivity", "kind", "ellipsoid_index")
        }
        ellipsoid_data: list[np.ndarray] = []
        ellipsoid_extent: list[np.ndarray] = []
        vertices: list[np.ndarray] = []
        faces: list[np.ndarray] = []
        triangle: list[np.ndarray] = []
        ids, kinds, counts, shape_of, vertex_offset, vertex_counts = [], [], [], [], [], []
        offset = n_vertices = n_ellipsoids = 0
        for index, shape in enumerate(shapes):
            params = mi.traverse(shape)
            ellipsoids = is_ellipsoids(params)
            mesh = not ellipsoids and isinstance(shape, mi.Mesh) and "vertex_positions" in params
            count = shape.primitive_count()
            if ellipsoids:
                data = np.asarray(params["data"], dtype=np.float32)
                check_ellipsoids(shape.id(), data.reshape(-1, ELLIPSOID_STRIDE), float(params["extent"]))
                count = data.size // ELLIPSOID_STRIDE
                ellipsoid_data.append(data)
                ellipsoid_extent.append(np.full(count, float(params["extent"]), np.float32))
                columns["ellipsoid_index"].append(n_ellipsoids + np.arange(count, dtype=np.uint32))
                n_ellipsoids += count
            else:
                columns["ellipsoid_index"].append(np.zeros(count, np.uint32))
            if mesh:
                v = np.asarray(params["vertex_positions"], np.float32)
                vertices.append(v)
                faces.append(np.asarray(params["faces"], np.uint32) + n_vertices)
                vertex_offset.append(n_vertices)
                vertex_counts.append(v.size // 3)
                n_vertices += v.size // 3
            else:
                faces.append(np.zeros(3 * count, np.uint32))
                vertex_offset.append(-1)
                vertex_counts.append(0)
            triangle.append(np.full(count, mesh))
            material = lidar_material(shape)
            defaults = {
                "p_hit": material.p_hit if material else 1.0,
                "range_sigma": material.range_sigma if material else np.nan,
                "label": material.label if material else 0,
                "reflectivity": material.reflectivity if material else DEFAULT_REFLECTIVITY,
            }
            for name, default in defaults.items():
                values = element_attribute(shape, params, name, count, ellipsoids)
                dtype = np.uint32 if name == "label" else np.float32
                if values is None:  # one value for the whole shape: check it once
                    check_element_values(shape.id(), name, np.array([default], np.float64))
                    values = np.full(count, default, dtype)
                else:
                    check_element_values(shape.id(), name, values)
                columns[name].append(values.astype(dtype, copy=False))
            columns["kind"].append(np.full(count, ELLIPSOID if ellipsoids else SURFACE, np.uint32))
            shape_of.append(np.full(count, index, np.uint32))
            rid = registry_id(shape)
            element_offset[rid] = offset
            shape_index[rid] = index
            offset += count
            ids.append(shape.id())
            kinds.append("ellipsoids" if ellipsoids else "mesh" if mesh else "surface")
            counts.append(count)
        cat = {k: v[0] if len(v) == 1 else np.concatenate(v) for k, v in columns.items()}
        return cls(
            shape_ids=ids,
            shape_kinds=kinds,
            element_counts=counts,
            element_offset=mi.UInt32(element_offset),
            shape_index=mi.UInt32(shape_index),
            p_hit=mi.Float(cat["p_hit"]),
            range_sigma=mi.Float(cat["range_sigma"]),
            label=mi.UInt32(cat["label"]),
            reflectivity=mi.Float(cat["reflectivity"]),
            kind=mi.UInt32(cat["kind"]),
            element_shape=mi.UInt32(np.concatenate(shape_of)),
            ellipsoid_data=mi.Float(
                np.concatenate(ellipsoid_data) if ellipsoid_data else np.zeros(ELLIPSOID_STRIDE, np.float32)
            ),
            ellipsoid_extent=mi.Float(np.concatenate(ellipsoid_extent) if ellipsoid_extent else np.ones(1, np.float32)),
            ellipsoid_index=mi.UInt32(cat["ellipsoid_index"]),
            vertex_positions=mi.Float(np.concatenate(vertices) if vertices else np.zeros(3, np.float32)),
            face_vertices=mi.UInt32(np.concatenate(faces)),
            is_triangle=mi.Bool(np.concatenate(triangle)),
            vertex_offset=vertex_offset,
            vertex_counts=vertex_counts,
            ray_length=mitsuba_ray_length(
                np.concatenate(
                    [ellipsoid_sizes(d, e) for d, e in zip(ellipsoid_data, ellipsoid_extent)] or [np.zeros((0, 3))]
                )
            ),
        )

    @classmethod
    def from_elements(
        cls,
        p_hit: np.ndarray,
        label: np.ndarray | None = None,
        range_sigma: np.ndarray | None = None,
        reflectivity: np.ndarray | None = None,
    ) -> ElementTable:
        """A table of surface elements without scene geometry (segments traced by another tracer).

        Their segments come from cached distributions only (:meth:`cached_segment`), e.g. the cells
        a planar log's ray march met (:func:`mi_lidar.core.trace.rounds_from_segments`).
        """
        n = int(np.size(p_hit))
        check_element_values("elements", "p_hit", np.asarray(p_hit, np.float64))
        zeros = np.zeros(n, np.uint32)
        return cls(
            shape_ids=["elements"],
            shape_kinds=["surface"],
            element_counts=[n],
            element_offset=mi.UInt32([0]),
            shape_index=mi.UInt32([0]),
            p_hit=mi.Float(np.asarray(p_hit, np.float32)),
            range_sigma=mi.Float(
                np.full(n, np.nan, np.float32) if range_sigma is None else np.asarray(range_sigma, np.float32)
            ),
            label=mi.UInt32(zeros if label is None else np.asarray(label, np.uint32)),
            reflectivity=mi.Float(
                np.full(n, DEFAULT_REFLECTIVITY, np.float32)
                if reflectivity is None
                else np.asarray(reflectivity, np.float32)
            ),
            kind=mi.UInt32(np.full(n, SURFACE, np.uint32)),
            element_shape=mi.UInt32(zeros),
            ellipsoid_data=mi.Float(np.zeros(ELLIPSOID_STRIDE, np.float32)),
            ellipsoid_extent=mi.Float([1.0]),
            ellipsoid_index=mi.UInt32(zeros),
            vertex_positions=mi.Float(np.zeros(3, np.float32)),
            face_vertices=mi.UInt32(np.zeros(3 * n, np.uint32)),
            is_triangle=mi.Bool(np.zeros(n, bool)),
            vertex_offset=[-1],
            vertex_counts=[0],
        )

    def replaced(self, **arrays) -> ElementTable:
        """A shallow copy with some arrays replaced (for example by differentiable ones)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(arrays)
        return ElementTable(**values)

    def element_of(self, si) -> mi.UInt32:
        """Global element index of each intersection."""
        rid = dr.reinterpret_array(mi.UInt32, si.shape)
        return dr.gather(mi.UInt32, self.element_offset, rid, si.is_valid()) + si.prim_index

    # ------------------------------------------------------------------ shared per-element values
    def _properties(self, element: mi.UInt32, valid: mi.Bool, default_sigma: float) -> ElementValues:
        """The values of ``element``: hit probability, range sigma (m, the sensor's where unset), kind, shape,
        label and reflectivity."""
        sigma = lookup(self.range_sigma, element, valid)  # lookup: fitted tables get reproducible gradients
        return ElementValues(
            lookup(self.p_hit, element, valid),
            dr.select(dr.isnan(sigma), default_sigma, sigma),
            dr.gather(mi.UInt32, self.kind, element, valid),
            dr.gather(mi.UInt32, self.element_shape, element, valid),
            dr.gather(mi.UInt32, self.label, element, valid),
            lookup(self.reflectivity, element, valid),
        )

    def _ellipsoid(self, element: mi.UInt32, active: mi.Bool):
        """Center, scale, quaternion and extent of the ellipsoid elements ``element`` (identity elsewhere)."""
        e = dr.gather(mi.UInt32, self.ellipsoid_index, element, active)
        data = [lookup(self.ellipsoid_data, e * ELLIPSOID_STRIDE + i, active) for i in range(ELLIPSOID_STRIDE)]
        center = mi.Point3f(*data[0:3])
        scale = dr.select(active, mi.Vector3f(*data[3:6]), 1.0)
        quat = dr.select(active, mi.Vector4f(*data[6:10]), mi.Vector4f(0, 0, 0, 1))
        return center, scale, quat, dr.gather(mi.Float, self.ellipsoid_extent, e, active)

    def ellipsoid_entry(self, element: mi.UInt32, valid: mi.Bool, origin, direction):
        """Where rays ``(origin, direction)`` enter the traced surfaces of the ellipsoids they met: ``(inside, entry)``.

        The traced surface is the element's at ``extent`` sigmas, widened by the margin of
        :mod:`~mi_lidar.core.smoothing` while ``smoothing`` > 0 (the scene then holds inflated
        ellipsoids). ``inside`` marks the lanes where ``element`` is an ellipsoid and the ray passes
        inside that surface; ``entry`` is there in m from ``origin``.
        """
        from mi_lidar.core.smoothing import REACH

        is_ellipsoid = valid & (dr.gather(mi.UInt32, self.kind, element, valid) == ELLIPSOID)
        center, scale, quat, extent = self._ellipsoid(element, is_ellipsoid)
        if self.smoothing > 0:  # a kernel input: annealing does not recompile
            extent = extent + dr.opaque(mi.Float, REACH * self.smoothing)
        _, _, lo, hi = ray_restricted_gaussian(center, scale, quat, extent, origin, direction)
        return is_ellipsoid & (hi > lo), lo

    # ------------------------------------------------------------------ segments
    def traced_segment(self, si, valid, element, origin, direction, default_sigma: float) -> Segment:
        """The :class:`Segment` of Mitsuba intersections ``si`` of rays ``(origin, direction)`` (sampler).

        Args:
            si: surface interactions of this round (``mi.RayFlags.Minimal`` suffices).
            valid: lanes whose ray met an element within range.
            element: global element indices (``element_of(si)``).
            origin, direction: the *original* ray origin and unit direction (the range is measured
                from the origin, not from where the ray restarted).
            default_sigma: the sensor's range sigma (m), used where an element has none.
        """
        nominal = dr.dot(si.p - origin, direction)
        values = self._properties(element, valid, default_sigma)
        is_ellipsoid = valid & (values.kind == ELLIPSOID)
        if self.has_ellipsoids:  # the range of an ellipsoid is its chord's entry, as in :meth:`segment`
            center, scale, quat, extent = self._ellipsoid(element, is_ellipsoid)
            restricted = ray_restricted_gaussian(center, scale, quat, extent, origin, direction)
            nominal = dr.select(is_ellipsoid, restricted[2], nominal)
        else:  # no lane is an ellipsoid: skip their gathers (every lane selects the surface values)
            restricted = (nominal, values.sigma, nominal, nominal)
        corner = (None, None)
        if self.has_triangles:
            triangle = valid & dr.gather(mi.Bool, self.is_triangle, element, valid)
            v0, v1, v2 = (self._vertex(element, c, triangle) for c in range(3))
            corner = corners(v0, v1, v2, triangle, origin, direction, nominal)
        return element_segment(
            valid, element, values, is_ellipsoid, nominal, restricted, dr.abs(dr.dot(si.n, direction)), corner
        )

    def _vertex(self, element: mi.UInt32, corner: int, active: mi.Bool) -> mi.Point3f:
        index = dr.gather(mi.UInt32, self.face_vertices, 3 * element + corner, active)
        return mi.Point3f(*[lookup(self.vertex_positions, 3 * index + i, active) for i in range(3)])

    def segment(self, entry, valid, element, origin, direction, default_sigma: float) -> Segment:
        """The :class:`Segment` of ``element`` along rays ``(origin, direction)``, from the table's geometry.

        Differentiable in ``vertex_positions``, ``ellipsoid_data``, ``p_hit``, ``range_sigma`` and in
        the rays. The range of a triangle is the distance to its plane; of an ellipsoid, the entry
        into its chord (the Gaussian restricted to the ray gives the return distribution); of any
        other shape, the distance to the tangent plane at the traced point ``entry.point`` (normal
        ``entry.normal``), exact for planes and to first order elsewhere.

        Args:
            entry: the traced values of the same lanes (``point``, ``normal``: a
                :class:`~mi_lidar.core.trace.Round` or anything with those fields).
            valid: lanes whose ray met an element.
            element: global element indices.
            origin, direction: the ray origins (m) and unit directions the range is measured from.
            default_sigma: the sensor's range sigma (m), used where an element has none.
        """
        from mi_lidar.core.smoothing import presence

        values = self._properties(element, valid, default_sigma)
        triangle = valid & dr.gather(mi.Bool, self.is_triangle, element, valid)

        # ---------------- Triangles: plane of the face; other surfaces: traced tangent plane ----
        v0, v1, v2 = (self._vertex(element, c, triangle) for c in range(3))
        normal = dr.select(triangle, dr.normalize(dr.cross(v1 - v0, v2 - v0)), dr.detach(entry.normal))
        anchor = dr.select(triangle, v0, dr.detach(entry.point))
        d_n = dr.dot(direction, normal)
        safe_d_n = dr.select(dr.abs(d_n) > 1e-12, d_n, 1e-12)
        t_plane = dr.dot(anchor - origin, normal) / safe_d_n

        # ---------------- Ellipsoids: Gaussian restricted to the ray, entry at the chord --------
        is_ellipsoid = valid & (values.kind == ELLIPSOID)
        center, scale, quat, extent = self._ellipsoid(element, is_ellipsoid)
        e_mean, e_sigma, e_lo, e_hi = ray_restricted_gaussian(center, scale, quat, extent, origin, direction)
        point = origin + e_lo * direction
        local_gradient = rotate_inverse(quat, point - center) / (scale * scale)
        e_normal = rotate_inverse(mi.Vector4f(-quat.x, -quat.y, -quat.z, quat.w), local_gradient)
        e_cos = dr.abs(dr.dot(dr.normalize(e_normal), direction))
        if self.smoothing > 0:
            _, _, closest_sq = ray_closest_approach(center, scale, quat, origin, direction)
            soft = presence(closest_sq, extent, self.smoothing)
            values = values._replace(p=dr.select(is_ellipsoid, values.p * soft, values.p))

        return element_segment(
            valid,
            element,
            values,
            is_ellipsoid,
            dr.select(is_ellipsoid, e_lo, t_plane),
            (e_mean, e_sigma, e_lo, e_hi),
            dr.select(is_ellipsoid, e_cos, dr.abs(d_n)),
            corners(v0, v1, v2, triangle, origin, direction, t_plane) if self.has_triangles else (None, None),
        )

    def cached_segment(self, entry, valid: mi.Bool, default_sigma: float) -> Segment:
        """The :class:`Segment` of a traced entry whose geometry was computed once (rays and geometry fixed).

        Only the per-element values that can be fitted without moving anything are read from the
        table (hit probability, and range sigma of surfaces), so gradients reach them.

        Args:
            entry: a :class:`~mi_lidar.core.trace.Round` (or a gathered view of one) holding
                ``element``, ``nominal``, ``cos_incidence`` and ``cached`` = ``(mean, sigma, lo, hi)``
                of the return distribution before effects (m; ``sigma`` is used for ellipsoids only),
                followed by the 3 corner offsets (m) and 3 corner weights where the tracer knew them.
            valid: lanes that hold an entry (the others read nothing).
            default_sigma: the sensor's range sigma (m), used where an element has none.
        """
        mean, e_sigma, lo, hi = entry.cached[:4]
        corner = entry.cached[4:]
        values = self._properties(entry.element, valid, default_sigma)
        return Segment(
            valid=valid,
            nominal=entry.nominal,
            mean=mean,
            lo=lo,
            hi=hi,
            cos_incidence=entry.cos_incidence,
            element=entry.element,
            corner_offset=mi.Vector3f(*corner[:3]) if corner else None,
            corner_weight=mi.Vector3f(*corner[3:]) if corner else None,
            **values._replace(sigma=dr.select(values.kind == ELLIPSOID, e_sigma, values.sigma))._asdict(),
        )
