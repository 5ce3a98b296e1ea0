"""Differentiable element geometry and the rays of logs.

Calibration traces every ray once without gradients (:mod:`mi_lidar.calibration.records`: per
entry the element met, the traced nominal range and incidence). :class:`DiffTable` then rebuilds
each segment *with* gradients from flat arrays: the triangle entry distance
``t = dot(v0 - o, n) / dot(d, n)`` from the vertex positions, and the ellipsoid chord from the
``ellipsoid_data`` array, so gradients reach vertex heights, ellipsoid centers and scales, and
(through the rays) the sensor intrinsics and extrinsics. When nothing fitted moves rays or
geometry, :meth:`DiffTable.cached_segment` reads the geometry computed once and only gathers the
fitted per-element values. :mod:`mi_lidar.calibration.likelihood` evaluates the pass-through
mixture on these segments.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.calibration.smoothing import presence
from mi_lidar.core.elements import ELLIPSOID_STRIDE, ElementTable, ordered_shapes
from mi_lidar.core.rays import LogRays  # noqa: F401  (the one Log -> RayBatch builder, used by fit)
from mi_lidar.core.segment import ELLIPSOID, Segment, ray_quadratic, ray_restricted_gaussian, rotate_inverse


@dataclass
class DiffTable(ElementTable):
    """An :class:`ElementTable` whose segments are recomputed from differentiable geometry.

    Attributes:
        vertex_positions: all meshes' vertices, flat (3 V) floats, m.
        face_vertices: per element, 3 global vertex indices, flat (3 n_elements) (0 for non-triangles).
        is_triangle: per element, True for mesh triangles.
        element_shape: per element, index of its shape in ``shape_ids``.
        vertex_offset: per shape, index of its first vertex in ``vertex_positions`` (-1 if not a mesh).
        vertex_counts: per shape, vertex count (0 if not a mesh).
        smoothing: > 0 while fitting ellipsoid geometry: ellipsoids return with the soft
            silhouette of :mod:`~mi_lidar.calibration.smoothing` (sigmas of the element); 0 is exact.
    """

    vertex_positions: mi.Float = None
    face_vertices: mi.UInt32 = None
    is_triangle: mi.Bool = None
    element_shape: mi.UInt32 = None
    vertex_offset: list = None
    vertex_counts: list = None
    smoothing: float = 0.0

    @classmethod
    def from_scene(cls, scene) -> DiffTable:
        """The table of a loaded scene plus its meshes' vertices and faces."""
        base = ElementTable.from_scene(scene)
        vertices, faces, triangle, shape_of, vertex_offset, vertex_counts = [], [], [], [], [], []
        n_vertices = 0
        for index, shape in enumerate(ordered_shapes(scene)):
            count = base.element_counts[index]
            shape_of.append(np.full(count, index, np.uint32))
            if isinstance(shape, mi.Mesh) and base.shape_kinds[index] == "surface":
                params = mi.traverse(shape)
                v = np.asarray(params["vertex_positions"], np.float32)
                vertices.append(v)
                faces.append(np.asarray(params["faces"], np.uint32) + n_vertices)
                triangle.append(np.ones(count, bool))
                vertex_offset.append(n_vertices)
                vertex_counts.append(v.size // 3)
                n_vertices += v.size // 3
            else:
                faces.append(np.zeros(3 * count, np.uint32))
                triangle.append(np.zeros(count, bool))
                vertex_offset.append(-1)
                vertex_counts.append(0)
        return cls(
            **{f.name: getattr(base, f.name) for f in fields(ElementTable)},
            vertex_positions=mi.Float(np.concatenate(vertices) if vertices else np.zeros(3, np.float32)),
            face_vertices=mi.UInt32(np.concatenate(faces)),
            is_triangle=mi.Bool(np.concatenate(triangle)),
            element_shape=mi.UInt32(np.concatenate(shape_of)),
            vertex_offset=vertex_offset,
            vertex_counts=vertex_counts,
        )

    def replaced(self, **arrays) -> DiffTable:
        """A shallow copy with some arrays replaced (for example by differentiable ones)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(arrays)
        return DiffTable(**values)

    def _vertex(self, element: mi.UInt32, corner: int, active: mi.Bool) -> mi.Point3f:
        index = dr.gather(mi.UInt32, self.face_vertices, 3 * element + corner, active)
        return mi.Point3f(*[dr.gather(mi.Float, self.vertex_positions, 3 * index + i, active) for i in range(3)])

    def segment(self, si, valid, element, origin, direction, default_sigma: float) -> Segment:
        """The :class:`Segment` of element ``element`` along rays ``(origin, direction)``, with gradients.

        Args:
            si: the traced values (``nominal`` range in m and ``cos_incidence``) of the same lanes,
                used only for shapes that are neither meshes nor ellipsoids, whose geometry is
                not differentiable here (a :class:`~mi_lidar.calibration.records.Round`).
            valid: lanes whose ray met an element.
            element: global element indices.
            origin, direction: the ray origins (m) and unit directions the range is measured from.
            default_sigma: the sensor's range sigma (m), used where an element has none.
        """
        p = dr.gather(mi.Float, self.p_hit, element, valid)
        sigma = dr.gather(mi.Float, self.range_sigma, element, valid)
        sigma = dr.select(dr.isnan(sigma), default_sigma, sigma)
        kind = dr.gather(mi.UInt32, self.kind, element, valid)
        triangle = valid & dr.gather(mi.Bool, self.is_triangle, element, valid)

        # ---------------- Triangles: plane of the face, entry distance and incidence --------
        v0, v1, v2 = (self._vertex(element, c, triangle) for c in range(3))
        normal = dr.normalize(dr.cross(v1 - v0, v2 - v0))
        d_n = dr.dot(direction, normal)
        safe_d_n = dr.select(dr.abs(d_n) > 1e-12, d_n, 1e-12)
        t_triangle = dr.dot(v0 - origin, normal) / safe_d_n

        # ---------------- Ellipsoids: Gaussian restricted to the ray, entry at the chord ----
        is_ellipsoid = valid & (kind == ELLIPSOID)
        e = dr.gather(mi.UInt32, self.ellipsoid_index, element, is_ellipsoid)
        data = [
            dr.gather(mi.Float, self.ellipsoid_data, e * ELLIPSOID_STRIDE + i, is_ellipsoid)
            for i in range(ELLIPSOID_STRIDE)
        ]
        center = mi.Point3f(*data[0:3])
        scale = dr.select(is_ellipsoid, mi.Vector3f(*data[3:6]), 1.0)
        quat = dr.select(is_ellipsoid, mi.Vector4f(*data[6:10]), mi.Vector4f(0, 0, 0, 1))
        extent = dr.gather(mi.Float, self.ellipsoid_extent, e, is_ellipsoid)
        e_mean, e_sigma, e_lo, e_hi = ray_restricted_gaussian(center, scale, quat, extent, origin, direction)
        entry = origin + e_lo * direction
        local_gradient = rotate_inverse(quat, entry - center) / (scale * scale)
        e_normal = rotate_inverse(mi.Vector4f(-quat.x, -quat.y, -quat.z, quat.w), local_gradient)
        e_cos = dr.abs(dr.dot(dr.normalize(e_normal), direction))
        if self.smoothing > 0:
            soft = presence(*ray_quadratic(center, scale, quat, origin, direction), extent, self.smoothing)
            p = dr.select(is_ellipsoid, p * soft, p)

        nominal = dr.select(triangle, t_triangle, dr.select(is_ellipsoid, e_lo, si.nominal))
        cos_incidence = dr.select(triangle, dr.abs(d_n), dr.select(is_ellipsoid, e_cos, si.cos_incidence))
        return Segment(
            valid=valid,
            nominal=nominal,
            p=p,
            mean=dr.select(is_ellipsoid, e_mean, nominal),
            sigma=dr.select(is_ellipsoid, e_sigma, sigma),
            lo=dr.select(is_ellipsoid, e_lo, -dr.inf),
            hi=dr.select(is_ellipsoid, e_hi, dr.inf),
            cos_incidence=cos_incidence,
            element=element,
            shape=dr.gather(mi.UInt32, self.element_shape, element, valid),
            label=dr.gather(mi.UInt32, self.label, element, valid),
            kind=kind,
        )

    def cached_segment(
        self,
        element: mi.UInt32,
        nominal: mi.Float,
        cos_incidence: mi.Float,
        cached: tuple,
        default_sigma: float,
        valid: mi.Bool,
    ) -> Segment:
        """The :class:`Segment` of ``element`` from geometry computed once (rays and geometry fixed).

        Only the per-element values that can be fitted without moving anything are read from the
        table (hit probability, and range sigma of surfaces), so gradients reach them.

        Args:
            element: global element indices, one lane per entry.
            nominal, cos_incidence: traced nominal range (m) and |cos| of the incidence.
            cached: ``(mean, sigma, lo, hi)`` of the return distribution before effects (m), as
                :meth:`segment` computed them (``sigma`` is used for ellipsoids only).
            default_sigma: the sensor's range sigma (m), used where an element has none.
            valid: lanes that hold an entry (the others read nothing).
        """
        mean, e_sigma, lo, hi = cached
        kind = dr.gather(mi.UInt32, self.kind, element, valid)
        sigma = dr.gather(mi.Float, self.range_sigma, element, valid)
        sigma = dr.select(kind == ELLIPSOID, e_sigma, dr.select(dr.isnan(sigma), default_sigma, sigma))
        return Segment(
            valid=valid,
            nominal=nominal,
            p=dr.gather(mi.Float, self.p_hit, element, valid),
            mean=mean,
            sigma=sigma,
            lo=lo,
            hi=hi,
            cos_incidence=cos_incidence,
            element=element,
            shape=dr.gather(mi.UInt32, self.element_shape, element, valid),
            label=dr.gather(mi.UInt32, self.label, element, valid),
            kind=kind,
        )
