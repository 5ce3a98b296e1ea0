"""Mitsuba scene dicts from element sets, and saving them as XML plus PLY assets.

An element set is what the hybrid-scene pipeline fits and what calibration adjusts: a triangle
mesh with per-face Lidar values (:class:`MeshElements`), a set of Gaussian ellipsoids
(:class:`EllipsoidElements`) or one analytic shape such as a cylinder (:class:`AnalyticElements`).
:func:`scene_dict` turns a mapping ``id -> element set`` into a
dict for ``mi.load_dict``; :func:`save_scene` writes the same scene as XML plus PLY assets that
load back unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.scene.files import ShapeEntry, write_ellipsoids_ply, write_mesh_ply, write_scene_xml


@dataclass
class MeshElements:
    """A triangle mesh with per-face Lidar values.

    Attributes:
        vertices: (V, 3) positions, m.
        faces: (F, 3) vertex indices.
        p_hit: (F,) hit probabilities in [0, 1].
        range_sigma: (F,) range standard deviations (m), or None for the sensor default.
        label: (F,) class labels.
        reflectivity: (F,) Lambertian reflectivities, or None for the default.
    """

    vertices: np.ndarray
    faces: np.ndarray
    p_hit: np.ndarray
    label: np.ndarray
    range_sigma: np.ndarray | None = None
    reflectivity: np.ndarray | None = None


@dataclass
class EllipsoidElements:
    """Gaussian ellipsoids with per-ellipsoid Lidar values.

    Attributes:
        centers: (N, 3) means, m.
        scales: (N, 3) standard deviations along the principal axes, m.
        quaternions: (N, 4) rotations (x, y, z, w).
        p_hit: (N,) hit probabilities in [0, 1].
        label: (N,) class labels.
        extent: Mahalanobis radius of the element surfaces, in sigmas.
        reflectivity: (N,) Lambertian reflectivities, or None for the default.
    """

    centers: np.ndarray
    scales: np.ndarray
    quaternions: np.ndarray
    p_hit: np.ndarray
    label: np.ndarray
    extent: float = 3.0
    reflectivity: np.ndarray | None = None


@dataclass
class AnalyticElements:
    """A Mitsuba analytic shape (sphere, disk: one element; a cylinder loads as a mesh of ``2 n`` triangles,
    :mod:`mi_lidar.scene.cylinders`) with its Lidar values.

    Attributes:
        plugin: Mitsuba shape plugin, one of :data:`~mi_lidar.scene.files.ANALYTIC_SHAPES`.
        to_world: (4, 4) object-to-world matrix (m) placing Mitsuba's unit shape.
        p_hit: hit probability in [0, 1].
        label: class label.
        range_sigma: range standard deviation (m), or None for the sensor default.
    """

    plugin: str
    to_world: np.ndarray
    p_hit: float
    label: int
    range_sigma: float | None = None

    def material(self) -> dict:
        """The nested ``lidar_material`` as a dict for ``mi.load_dict``."""
        material = {"type": "lidar_material", "p_hit": float(self.p_hit), "label": int(self.label)}
        if self.range_sigma is not None:
            material["range_sigma"] = float(self.range_sigma)
        return material


def _column(values, n: int, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float32).reshape(-1)
    if array.size != n:
        raise ParameterError(f"{name} has {array.size} values for {n} elements; give one per element")
    return array


def mesh_object(name: str, elements: MeshElements):
    """A ``mi.Mesh`` holding the triangles and face attributes ``face_p_hit``, ``face_label``,
    ``face_range_sigma`` and ``face_reflectivity``."""
    vertices = np.asarray(elements.vertices, dtype=np.float32)
    faces = np.asarray(elements.faces, dtype=np.uint32)
    mesh = mi.Mesh(name, len(vertices), len(faces), has_vertex_normals=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    columns = {"p_hit": elements.p_hit, "label": elements.label}
    for key in ("range_sigma", "reflectivity"):
        if getattr(elements, key) is not None:
            columns[key] = getattr(elements, key)
    for key, values in columns.items():
        mesh.add_attribute(f"face_{key}", 1, mi.Float(_column(values, len(faces), key)))
    return mesh


def ellipsoids_dict(elements: EllipsoidElements) -> dict:
    """The ``ellipsoids`` shape dict of an ellipsoid set (attributes as (N, 1) tensors)."""
    n = len(elements.centers)
    tensor = lambda a, w: mi.TensorXf(np.asarray(a, dtype=np.float32).reshape(n, w))  # noqa: E731
    extras = (
        {}
        if elements.reflectivity is None
        else {"reflectivity": tensor(_column(elements.reflectivity, n, "reflectivity"), 1)}
    )
    return {
        **extras,
        "type": "ellipsoids",
        "extent": float(elements.extent),
        "centers": tensor(elements.centers, 3),
        "scales": tensor(elements.scales, 3),
        "quaternions": tensor(elements.quaternions, 4),
        "p_hit": tensor(_column(elements.p_hit, n, "p_hit"), 1),
        "label": tensor(_column(elements.label, n, "label"), 1),
    }


def scene_dict(element_sets: dict, sensor: dict | None = None, integrator: dict | None = None) -> dict:
    """A scene dict for ``mi.load_dict`` from ``{shape id: MeshElements | EllipsoidElements}``."""
    scene = {"type": "scene"}
    for key, elements in element_sets.items():
        if isinstance(elements, MeshElements):
            scene[key] = mesh_object(key, elements)
        elif isinstance(elements, EllipsoidElements):
            scene[key] = ellipsoids_dict(elements)
        elif isinstance(elements, AnalyticElements):
            scene[key] = {
                "type": elements.plugin,
                "to_world": mi.ScalarTransform4f(np.asarray(elements.to_world, np.float64)),
                "bsdf": elements.material(),
            }
        else:
            raise ParameterError(
                f"element set {key!r} is a {type(elements).__name__}; "
                "expected MeshElements, EllipsoidElements or AnalyticElements"
            )
    if sensor is not None:
        scene["sensor"] = sensor
    if integrator is not None:
        scene["integrator"] = integrator
    return scene


def save_scene(path, element_sets: dict, extra_xml: str = "") -> Path:
    """Write ``element_sets`` as a scene XML at ``path`` with PLY assets in ``<stem>_assets/``."""
    path = Path(path)
    assets = path.parent / f"{path.stem}_assets"
    entries = []
    for key, elements in element_sets.items():
        filename = assets / f"{key}.ply"
        if isinstance(elements, MeshElements):
            write_mesh_ply(
                filename,
                elements.vertices,
                elements.faces,
                p_hit=elements.p_hit,
                range_sigma=elements.range_sigma,
                label=elements.label,
                reflectivity=elements.reflectivity,
            )
            entries.append(ShapeEntry(id=key, kind="mesh", filename=f"{assets.name}/{key}.ply"))
        elif isinstance(elements, AnalyticElements):
            entries.append(
                ShapeEntry(
                    id=key,
                    kind=elements.plugin,
                    to_world=elements.to_world,
                    p_hit=float(elements.p_hit),
                    range_sigma=elements.range_sigma,
                    label=int(elements.label),
                )
            )
        else:
            write_ellipsoids_ply(
                filename,
                elements.centers,
                elements.scales,
                elements.quaternions,
                p_hit=elements.p_hit,
                label=elements.label,
                reflectivity=elements.reflectivity,
            )
            entries.append(
                ShapeEntry(id=key, kind="ellipsoids", filename=f"{assets.name}/{key}.ply", extent=elements.extent)
            )
    return write_scene_xml(
        path, entries, header_comment="written by mi_lidar.calibration.save_scene", extra_xml=extra_xml
    )
