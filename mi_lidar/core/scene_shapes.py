"""The shapes of a loaded Mitsuba scene as the element table reads them: order, ids, materials, values.

:func:`ordered_shapes` fixes the order of the scene's shapes (the same on every load);
:func:`registry_id` is the value an intersection's ``si.shape`` carries for a shape;
:func:`element_attribute` reads a per-element attribute (mesh face property or ellipsoid tensor);
the checks refuse ellipsoids and per-element values that Mitsuba would use silently.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import SceneError
from mi_lidar.core.params import MAX_SIGMA_M, SIGMA_LIMIT, check_limit
from mi_lidar.core.trace import mitsuba_ray_length

ELLIPSOID_STRIDE = 10  # floats per ellipsoid in Mitsuba's `data`: center, scale, quaternion
QUATERNION_SLACK = 1e-3  # an ellipsoid's quaternion norm may differ from 1 by this much (float32 files)


def registry_id(shape) -> int:
    """Dr.Jit registry id of a shape (the value ``si.shape`` carries for it)."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def shape_order(shape) -> tuple:
    """Sort key of a shape in the table: its declared id, then its size and bounding box.

    ``scene.shapes()`` lists shapes in the order Mitsuba's parallel loader finished them, which
    changes from run to run under load; sorting by what the scene declares makes element and shape
    indices the same on every load (:func:`mi_lidar.scene.load_scene` also keeps Mitsuba from merging
    meshes that share a material into one unnamed mesh, so every declared id stays addressable).
    Unnamed shapes (empty id) are told apart by their primitive count and bounding box (m, rounded
    to 1 um).
    """
    box = shape.bbox()
    return (shape.id(), shape.primitive_count(), tuple(round(float(v), 6) for v in (*box.min, *box.max)))


def ordered_shapes(scene) -> list:
    """The scene's shapes in table order (:func:`shape_order`)."""
    return sorted(scene.shapes(), key=shape_order)


def lidar_material(shape):
    """The shape's ``lidar_material`` BSDF (anything holding ``p_hit``, ``range_sigma``, ``label`` and
    ``reflectivity``), or None."""
    bsdf = shape.bsdf()
    return bsdf if all(hasattr(bsdf, name) for name in ("p_hit", "range_sigma", "label", "reflectivity")) else None


def is_ellipsoids(params) -> bool:
    return "data" in params and "extent" in params


def element_attribute(shape, params, name: str, count: int, ellipsoids: bool) -> np.ndarray | None:
    """Per-element attribute ``name`` of ``shape`` as a numpy array, or None when absent."""
    if ellipsoids:
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


def ellipsoid_sizes(data: np.ndarray, extent) -> np.ndarray:
    """(N, 3) ``extent x scale`` (m) of ellipsoids ``data`` (10 floats each); ``extent`` one value or (N,)."""
    return np.asarray(data, np.float64).reshape(-1, ELLIPSOID_STRIDE)[:, 3:6] * np.reshape(extent, (-1, 1))


def scene_ray_length(scene) -> float:
    """:func:`~mi_lidar.core.trace.mitsuba_ray_length` of the ellipsoids of a loaded scene, m (1 without)."""
    sizes = [np.zeros((0, 3))]
    for shape in scene.shapes():
        params = mi.traverse(shape)
        if is_ellipsoids(params):
            sizes.append(ellipsoid_sizes(params["data"], float(params["extent"])))
    return mitsuba_ray_length(np.concatenate(sizes))


def check_ellipsoids(shape_id: str, data: np.ndarray, extent: float) -> None:
    """Refuse ellipsoids (N, 10) whose centre, scales or quaternion is not finite, whose scales are not > 0, or
    whose quaternion is not a unit one (Mitsuba turns it into a matrix as it is, the chords assume a rotation), and
    a set whose ``extent`` (sigmas) is not a finite number > 0 (0, NaN or inf: never met; -1: met, silently)."""
    if not 0 < extent < math.inf:
        raise SceneError(
            f"shape {shape_id!r}: extent={extent:g}; the ellipsoids' extent is how many sigmas each reaches, a finite "
            'number > 0 (default 3): fix <float name="extent" .../> in the scene'
        )
    norm = np.linalg.norm(data[:, 6:10].astype(np.float64), axis=1)
    bad = ~np.isfinite(data).all(axis=1) | np.any(data[:, 3:6] <= 0, axis=1) | (np.abs(norm - 1.0) > QUATERNION_SLACK)
    if bad.any():
        index = int(np.argmax(bad))
        center, scale, quat = (", ".join(f"{v:.4g}" for v in data[index, a:b]) for a, b in ((0, 3), (3, 6), (6, 10)))
        raise SceneError(
            f"shape {shape_id!r}: ellipsoid {index} (of {len(data)}, {int(bad.sum())} such) has center ({center}), "
            f"scales ({scale}), quaternion ({quat}): every ellipsoid needs a finite centre, finite scales > 0 m and "
            "a unit quaternion (x, y, z, w). Fix or drop it in the file (normalize the quaternions)."
        )


def check_element_values(shape_id: str, name: str, values: np.ndarray) -> None:
    """Validate per-element values of one shape."""
    if name == "p_hit" and (not np.all(np.isfinite(values)) or values.min() < 0 or values.max() > 1):
        raise SceneError(
            f"shape {shape_id!r}: p_hit must lie in [0, 1]; got values in [{np.nanmin(values):.3g}, "
            f"{np.nanmax(values):.3g}]. Clip the hit probabilities to [0, 1]."
        )
    if name == "reflectivity" and (not np.all(np.isfinite(values)) or np.any(values < 0)):
        raise SceneError(
            f"shape {shape_id!r}: reflectivity must be finite and >= 0 (1 = white diffuse target); got "
            f"{values[~(np.isfinite(values) & (values >= 0))][0]:.3g}. Fix the material or the PLY face property."
        )
    if name == "range_sigma":  # NaN: the element takes the sensor's range_sigma
        fix = "fix the material or the PLY face property"
        check_limit(
            f"shape {shape_id!r}", name, values, MAX_SIGMA_M, SIGMA_LIMIT, fix, unset_nan=True, error=SceneError
        )
