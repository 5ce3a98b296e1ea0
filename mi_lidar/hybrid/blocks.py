"""Scene files of a hybrid model: one ground mesh and one ellipsoid set per block (XML + PLY).

:func:`write_scene` writes ``<name>.xml`` plus ``<name>_assets/ground_b<k>.ply`` and
``ellipsoids_b<k>.ply`` with per-element ``p_hit``, ``range_sigma`` (0 for ellipsoids, whose
spread is their Gaussian) and ``label``, using :mod:`mi_lidar.scene.files`, and returns the paths
it wrote. Given a
:class:`SceneSensor`, the XML also holds a ``lidar`` sensor and a ``lidar_integrator``, so it
loads with :func:`mi_lidar.load_scene`, renders with ``mi.render`` and simulates with
:func:`mi_lidar.simulate`. :func:`read_scene` reads a scene back into a :class:`HybridModel`
(instances are not stored in the files).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
from plyfile import PlyData

from mi_lidar.core.errors import SceneError, unreadable
from mi_lidar.core.log import Log
from mi_lidar.core.patterns import to_table
from mi_lidar.core.patterns.from_log import pattern_from_log
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh, HybridModel
from mi_lidar.scene.files import ShapeEntry, write_ellipsoids_ply, write_mesh_ply, write_scene_xml
from mi_lidar.scene.rebase import UnsupportedTransform, matrix_value, to_world_matrix


@dataclass
class SceneSensor:
    """The ``lidar`` sensor and ``lidar_integrator`` written into a scene XML.

    Attributes:
        pattern: firing pattern name (e.g. ``"hdl32e"``) or path of a pattern table.
        pose: (4, 4) sensor-to-world transform.
        min_range, max_range: reported range limits, m.
        range_sigma: noise of elements without their own, m.
        max_segments: elements a ray may pass before it counts as a miss.
        firings: film width for named spinning patterns (None: the pattern's own).
    """

    pattern: str
    pose: np.ndarray
    min_range: float = 0.0
    max_range: float = 120.0
    range_sigma: float = 0.05
    max_segments: int = 16
    firings: int | None = None

    @classmethod
    def from_log(cls, log: Log, table_path, scan: int = 0) -> SceneSensor:
        """The sensor of ``log``: its scan-``scan`` pattern written to ``table_path`` (``.npy``) and pose."""
        table = to_table(pattern_from_log(log, scan), Path(table_path))
        return cls(
            str(table.resolve()),
            log.poses[scan],
            float(log.sensor.get("min_range", 0.0)),
            float(log.sensor.get("max_range", 120.0)),
        )

    def xml(self) -> str:
        """The ``<default>``, ``<integrator>`` and ``<sensor>`` elements.

        The pattern is a ``<default name="pattern">`` parameter, so
        ``mi_lidar.load_scene(xml, pattern="vlp16")`` swaps it.
        """
        matrix = matrix_value(self.pose)
        firings = "" if self.firings is None else f'\n        <integer name="firings" value="{int(self.firings)}"/>'
        return (
            f'    <default name="pattern" value={quoteattr(str(self.pattern))}/>\n'
            f'    <integrator type="lidar_integrator" id="integrator">\n'
            f'        <integer name="max_segments" value="{int(self.max_segments)}"/>\n'
            f"    </integrator>\n"
            f'    <sensor type="lidar" id="lidar">\n'
            f'        <string name="pattern" value="$pattern"/>{firings}\n'
            f'        <float name="min_range" value="{self.min_range:g}"/>\n'
            f'        <float name="max_range" value="{self.max_range:g}"/>\n'
            f'        <float name="range_sigma" value="{self.range_sigma:g}"/>\n'
            f'        <transform name="to_world"><matrix value="{matrix}"/></transform>\n'
            f"    </sensor>"
        )


def assets_folder(out_dir, name: str) -> Path:
    """The folder of scene ``name``'s assets beside its XML, ``<out_dir>/<name>_assets`` (created)."""
    folder = Path(out_dir) / f"{name}_assets"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def write_scene(model: HybridModel, out_dir, name: str = "scene", sensor: SceneSensor | None = None) -> list[Path]:
    """Write ``model`` as a Mitsuba scene.

    Args:
        model: the hybrid model; elements are grouped by their ``block``.
        out_dir: output folder (created).
        name: XML file stem; assets go to :func:`assets_folder`.
        sensor: sensor and integrator to include (None: shapes only).

    Returns:
        The paths written: the XML first, then its PLY assets in the XML's order
        (``xml, *assets = write_scene(...)``).
    """
    out_dir = Path(out_dir)
    assets = assets_folder(out_dir, name).name  # the XML names its assets relative to itself
    shapes, written = [], []
    g, e = model.ground, model.ellipsoids
    to_world = None
    if np.any(model.origin):  # elements in a local frame: each shape placed at its origin
        to_world = np.eye(4)
        to_world[:3, 3] = model.origin
    for b in np.unique(np.r_[g.block, e.block]):
        sel = g.block == b
        if sel.any():
            faces = g.faces[sel]
            used, inverse = np.unique(faces, return_inverse=True)
            fname = f"{assets}/ground_b{b}.ply"
            path = write_mesh_ply(
                out_dir / fname,
                g.vertices[used],
                inverse.reshape(-1, 3),
                p_hit=g.p_hit[sel],
                range_sigma=g.range_sigma[sel],
                label=g.label[sel],
            )
            written.append(path)
            shapes.append(ShapeEntry(id=f"ground_b{b}", kind="mesh", filename=fname, to_world=to_world))
        sel = e.block == b
        if sel.any():
            scales, quats = e.subset(sel).axes()
            fname = f"{assets}/ellipsoids_b{b}.ply"
            path = write_ellipsoids_ply(
                out_dir / fname,
                e.means[sel],
                scales,
                quats,
                p_hit=e.p_hit[sel],
                range_sigma=np.zeros(sel.sum()),
                label=e.label[sel],
            )
            written.append(path)
            shapes.append(
                ShapeEntry(
                    id=f"ellipsoids_b{b}", kind="ellipsoids", filename=fname, extent=model.extent, to_world=to_world
                )
            )
    comment = f"mi-lidar hybrid geometric scene: {len(g)} triangles, {len(e)} ellipsoids, {len(shapes)} shapes"
    xml = write_scene_xml(
        out_dir / f"{name}.xml", shapes, header_comment=comment, extra_xml=sensor.xml() if sensor is not None else ""
    )
    return [xml, *written]


def read_mesh_ply(path) -> GroundMesh:
    """A triangle mesh PLY written by :func:`mi_lidar.scene.files.write_mesh_ply`.

    Raises:
        SceneError: the file is missing, or not a PLY with ``x y z`` vertices and triangle faces.
    """
    try:
        ply = PlyData.read(str(path))
        v, f = ply["vertex"].data, ply["face"].data
        names = f.dtype.names
        get = lambda n: np.asarray(f[f"{n}_0"]) if f"{n}_0" in names else None
        label = get("label")
        faces = np.stack(f["vertex_indices"]) if len(f) else np.zeros((0, 3), np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and not 0 <= faces.min() <= faces.max() < len(v)):
            raise ValueError("faces must be triangles indexing the vertices")
        return GroundMesh(
            np.c_[v["x"], v["y"], v["z"]],
            faces,
            get("p_hit"),
            get("range_sigma"),
            None if label is None else label.astype(np.int32),
        )
    except FileNotFoundError:
        raise SceneError(f"{path}: no such triangle mesh file") from None
    except PermissionError:
        raise unreadable(path, "triangle mesh", SceneError) from None
    except Exception as exc:  # plyfile raises many types on malformed files; name the file either way
        raise SceneError(
            f"{path}: not a triangle mesh PLY ({type(exc).__name__}: {exc}); "
            "write one with mi_lidar.scene.files.write_mesh_ply or mi-lidar fit-scene"
        ) from None


def read_ellipsoids_ply(path) -> EllipsoidSet:
    """An ellipsoid PLY written by :func:`mi_lidar.scene.files.write_ellipsoids_ply`."""
    v = PlyData.read(str(path))["vertex"].data
    names = v.dtype.names
    scales = np.exp(np.c_[v["scale_0"], v["scale_1"], v["scale_2"]])
    quats = np.c_[v["rot_1"], v["rot_2"], v["rot_3"], v["rot_0"]]
    get = lambda n: np.asarray(v[f"{n}_0"]) if f"{n}_0" in names else None
    label = get("label")
    return EllipsoidSet.from_axes(
        np.c_[v["x"], v["y"], v["z"]],
        scales,
        quats,
        p_hit=get("p_hit"),
        label=None if label is None else label.astype(np.int32),
    )


def read_scene(xml_path) -> HybridModel:
    """Read a scene written by :func:`write_scene` (or any XML of ``ply`` and ``ellipsoids`` shapes)."""
    xml_path = Path(xml_path)
    if not xml_path.is_file():
        raise SceneError(f"{xml_path}: no such scene file")
    root = ET.parse(xml_path).getroot()
    grounds, ells, extent, origin = [], [], 3.0, np.zeros(3)
    for b, shape in enumerate(root.iter("shape")):
        transform = shape.find("transform[@name='to_world']")
        if transform is not None:  # the local origin of a georeferenced scene (write_scene's translation)
            try:
                origin = to_world_matrix(transform, {})[:3, 3]
            except UnsupportedTransform as exc:
                raise SceneError(f"{xml_path}: shape {shape.get('id')!r}: {exc}") from exc
        fname = next((s.get("value") for s in shape.iter("string") if s.get("name") == "filename"), None)
        if fname is None:
            raise SceneError(f"{xml_path}: shape {shape.get('id')!r} has no filename")
        if shape.get("type") == "ply":
            mesh = read_mesh_ply(xml_path.parent / fname)
            mesh.block[:] = b
            grounds.append(mesh)
        elif shape.get("type") == "ellipsoids":
            ell = read_ellipsoids_ply(xml_path.parent / fname)
            ell.block[:] = b
            ells.append(ell)
            extent = float(next((f.get("value") for f in shape.iter("float") if f.get("name") == "extent"), 3.0))
    return HybridModel(GroundMesh.concat(grounds), EllipsoidSet.concat(ells), extent, origin=origin)
