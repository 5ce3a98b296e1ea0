"""The element table: per-element Lidar properties of a loaded Mitsuba scene, in flat arrays.

Every triangle and every ellipsoid of the scene is an *element* with a global index. For each
shape of ``scene.shapes()`` the table records where its elements start; an intersection
``(si.shape, si.prim_index)`` maps to the global index
``element_offset[registry_id(si.shape)] + si.prim_index``, and per-element values are single
gathers from flat arrays. Calibration replaces those arrays (for example ``p_hit`` by the sigmoid
of a differentiable logit array) and gradients flow through the same gathers.

Values come, in order of precedence, from per-element attributes (mesh PLY face properties
``p_hit_0``, ``range_sigma_0``, ``label_0``; ellipsoid PLY extras or ``(N, 1)`` tensors ``p_hit``,
``range_sigma``, ``label``), from the shape's nested ``lidar_material``, and from defaults (opaque,
the sensor's ``range_sigma``, label 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import SceneError
from mi_lidar.core.segment import ELLIPSOID, SURFACE, Segment, ray_restricted_gaussian

ELLIPSOID_STRIDE = 10  # floats per ellipsoid in Mitsuba's `data`: center, scale, quaternion


def registry_id(shape) -> int:
    """Dr.Jit registry id of a shape (the value ``si.shape`` carries for it)."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def shape_order(shape) -> tuple:
    """Sort key of a shape in the table: its declared id, then its size and bounding box.

    ``scene.shapes()`` lists shapes in the order Mitsuba's parallel loader finished them, which
    changes from run to run under load; sorting by what the scene declares makes element and shape
    indices the same on every load. Unnamed shapes (empty id) are told apart by their primitive
    count and bounding box (m, rounded to 1 um).
    """
    box = shape.bbox()
    return (shape.id(), shape.primitive_count(), tuple(round(float(v), 6) for v in (*box.min, *box.max)))


def ordered_shapes(scene) -> list:
    """The scene's shapes in table order (:func:`shape_order`)."""
    return sorted(scene.shapes(), key=shape_order)


def lidar_material(shape):
    """The shape's ``lidar_material`` BSDF (anything holding ``p_hit``, ``range_sigma`` and ``label``), or None."""
    bsdf = shape.bsdf()
    return bsdf if all(hasattr(bsdf, name) for name in ("p_hit", "range_sigma", "label")) else None


def _is_ellipsoids(shape) -> bool:
    keys = set(mi.traverse(shape).keys())
    return "data" in keys and "extent" in keys


def _per_element(shape, name: str, count: int, ellipsoids: bool) -> np.ndarray | None:
    """Per-element attribute ``name`` of ``shape`` as a numpy array, or None when absent."""
    if ellipsoids:
        params = mi.traverse(shape)
        if name not in params:
            return None
        values = np.asarray(params[name], dtype=np.float64).ravel()
    else:
        if not (isinstance(shape, mi.Mesh) and shape.has_attribute(f"face_{name}")):
            return None
        values = np.asarray(shape.attribute_buffer(f"face_{name}"), dtype=np.float64).ravel()
    if values.size != count:
        raise SceneError(
            f"shape {shape.id()!r}: attribute {name!r} has {values.size} values for {count} elements; "
            "give exactly one value per element"
        )
    return values


@dataclass
class ElementTable:
    """Flat per-element arrays of a scene (see the module docstring).

    Attributes:
        shape_ids: Mitsuba ids of the shapes, in table order.
        shape_kinds: ``"surface"`` or ``"ellipsoids"`` per shape.
        element_offset: per registry id, index of the shape's first element.
        shape_index: per registry id, index of the shape in ``shape_ids``.
        ellipsoid_offset: per registry id, index of the shape's first ellipsoid in ``ellipsoid_data``.
        p_hit, range_sigma: per-element hit probability and range sigma (m); NaN sigma = sensor default.
        label: per-element class label.
        kind: per-element ``SURFACE`` or ``ELLIPSOID``.
        ellipsoid_data: all ellipsoids' (center, scale, quaternion), 10 floats each.
        ellipsoid_extent: per ellipsoid, extent in sigmas.
        ellipsoid_index: per element, index into the ellipsoid arrays (0 for surfaces).
    """

    shape_ids: list
    shape_kinds: list
    element_counts: list
    element_offset: mi.UInt32
    shape_index: mi.UInt32
    p_hit: mi.Float
    range_sigma: mi.Float
    label: mi.UInt32
    kind: mi.UInt32
    ellipsoid_data: mi.Float
    ellipsoid_extent: mi.Float
    ellipsoid_index: mi.UInt32

    @property
    def n_elements(self) -> int:
        return int(sum(self.element_counts))

    @classmethod
    def from_scene(cls, scene) -> ElementTable:
        """Build the table of a loaded scene; raise :class:`SceneError` on invalid values."""
        shapes = ordered_shapes(scene)
        if not shapes:
            raise SceneError("the scene has no shapes; add a mesh or an ellipsoid set")
        n_registry = max(registry_id(s) for s in shapes) + 1
        element_offset = np.zeros(n_registry, np.uint32)
        shape_index = np.zeros(n_registry, np.uint32)
        columns = {"p_hit": [], "range_sigma": [], "label": [], "kind": [], "ellipsoid_index": []}
        ellipsoid_data, ellipsoid_extent = [], []
        ids, kinds, counts = [], [], []
        offset = 0
        for index, shape in enumerate(shapes):
            ellipsoids = _is_ellipsoids(shape)
            if ellipsoids:
                params = mi.traverse(shape)
                data = np.asarray(params["data"], dtype=np.float32)
                count = data.size // ELLIPSOID_STRIDE
                base = sum(len(e) for e in ellipsoid_extent)
                ellipsoid_data.append(data)
                ellipsoid_extent.append(np.full(count, float(params["extent"]), np.float32))
                columns["ellipsoid_index"].append(base + np.arange(count, dtype=np.uint32))
            else:
                count = shape.face_count() if isinstance(shape, mi.Mesh) else 1
                columns["ellipsoid_index"].append(np.zeros(count, np.uint32))
            material = lidar_material(shape)
            defaults = {
                "p_hit": material.p_hit if material else 1.0,
                "range_sigma": material.range_sigma if material else np.nan,
                "label": material.label if material else 0,
            }
            for name, default in defaults.items():
                values = _per_element(shape, name, count, ellipsoids)
                values = np.full(count, default, np.float64) if values is None else values
                _check_values(shape.id(), name, values)
                columns[name].append(values)
            columns["kind"].append(np.full(count, ELLIPSOID if ellipsoids else SURFACE, np.uint32))
            rid = registry_id(shape)
            element_offset[rid] = offset
            shape_index[rid] = index
            offset += count
            ids.append(shape.id())
            kinds.append("ellipsoids" if ellipsoids else "surface")
            counts.append(count)
        cat = {k: np.concatenate(v) for k, v in columns.items()}
        return cls(
            shape_ids=ids,
            shape_kinds=kinds,
            element_counts=counts,
            element_offset=mi.UInt32(element_offset),
            shape_index=mi.UInt32(shape_index),
            p_hit=mi.Float(cat["p_hit"].astype(np.float32)),
            range_sigma=mi.Float(cat["range_sigma"].astype(np.float32)),
            label=mi.UInt32(cat["label"].astype(np.uint32)),
            kind=mi.UInt32(cat["kind"]),
            ellipsoid_data=mi.Float(
                np.concatenate(ellipsoid_data) if ellipsoid_data else np.zeros(ELLIPSOID_STRIDE, np.float32)
            ),
            ellipsoid_extent=mi.Float(np.concatenate(ellipsoid_extent) if ellipsoid_extent else np.ones(1, np.float32)),
            ellipsoid_index=mi.UInt32(cat["ellipsoid_index"]),
        )

    def element_of(self, si) -> mi.UInt32:
        """Global element index of each intersection."""
        rid = dr.reinterpret_array(mi.UInt32, si.shape)
        return dr.gather(mi.UInt32, self.element_offset, rid, si.is_valid()) + si.prim_index

    def segment(self, si, valid, element, origin, direction, default_sigma: float) -> Segment:
        """The :class:`Segment` of intersections ``si`` of rays ``(origin, direction)``.

        Args:
            si: surface interactions of this round (``mi.RayFlags.Minimal`` suffices).
            valid: lanes whose ray met an element within range.
            element: global element indices (``element_of(si)``).
            origin, direction: the *original* ray origin and unit direction (the range is
                measured from the origin, not from where the ray restarted).
            default_sigma: the sensor's range sigma (m), used where an element has none.
        """
        nominal = dr.dot(si.p - origin, direction)
        p = dr.gather(mi.Float, self.p_hit, element, valid)
        sigma = dr.gather(mi.Float, self.range_sigma, element, valid)
        sigma = dr.select(dr.isnan(sigma), default_sigma, sigma)
        kind = dr.gather(mi.UInt32, self.kind, element, valid)
        is_ellipsoid = valid & (kind == ELLIPSOID)
        e = dr.gather(mi.UInt32, self.ellipsoid_index, element, is_ellipsoid)

        def fetch(first: int, n: int):
            return [
                dr.gather(mi.Float, self.ellipsoid_data, e * ELLIPSOID_STRIDE + first + i, is_ellipsoid)
                for i in range(n)
            ]

        center = mi.Point3f(*fetch(0, 3))
        scale = mi.Vector3f(*fetch(3, 3))
        quat = mi.Vector4f(*fetch(6, 4))
        extent = dr.gather(mi.Float, self.ellipsoid_extent, e, is_ellipsoid)
        scale = dr.select(is_ellipsoid, scale, 1.0)
        quat = dr.select(is_ellipsoid, quat, mi.Vector4f(0, 0, 0, 1))
        e_mean, e_sigma, e_lo, e_hi = ray_restricted_gaussian(center, scale, quat, extent, origin, direction)
        return Segment(
            valid=valid,
            nominal=nominal,
            p=p,
            mean=dr.select(is_ellipsoid, e_mean, nominal),
            sigma=dr.select(is_ellipsoid, e_sigma, sigma),
            lo=dr.select(is_ellipsoid, e_lo, -dr.inf),
            hi=dr.select(is_ellipsoid, e_hi, dr.inf),
            cos_incidence=dr.abs(dr.dot(si.n, direction)),
            element=element,
            shape=dr.gather(mi.UInt32, self.shape_index, dr.reinterpret_array(mi.UInt32, si.shape), valid),
            label=dr.gather(mi.UInt32, self.label, element, valid),
            kind=kind,
        )


def _check_values(shape_id: str, name: str, values: np.ndarray) -> None:
    """Validate per-element values of one shape."""
    if name == "p_hit" and (not np.all(np.isfinite(values)) or values.min() < 0 or values.max() > 1):
        raise SceneError(
            f"shape {shape_id!r}: p_hit must lie in [0, 1]; got values in [{np.nanmin(values):.3g}, "
            f"{np.nanmax(values):.3g}]. Clip the hit probabilities to [0, 1]."
        )
    if name == "range_sigma" and np.nanmin(values, initial=0.0) < 0:
        raise SceneError(f"shape {shape_id!r}: range_sigma must be >= 0 m; got {np.nanmin(values):.3g}")
