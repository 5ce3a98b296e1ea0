"""Writers for scene assets: element PLY files and Mitsuba XML scenes.

Two element kinds make a scene (thesis ch. 4.3):

* **triangle meshes** (``<shape type="ply">``): per-face ``p_hit`` (hit probability),
  ``range_sigma`` (m) and ``label`` (class id) are PLY face properties named ``p_hit_0``,
  ``range_sigma_0`` and ``label_0``; Mitsuba loads them as mesh attributes ``face_p_hit`` ...
* **ellipsoid sets** (``<shape type="ellipsoids">``): Mitsuba's PLY layout, one vertex per
  ellipsoid: ``x y z nx ny nz [p_hit_0 range_sigma_0 label_0] scale_0..2 rot_0..3`` where the
  scales are stored as natural logs (Mitsuba applies ``exp``) and ``rot_0`` is the real part.
  Scales are the Gaussian's standard deviations along its principal axes (m); the shape's
  ``extent`` (in sigmas, default 3) is the Mahalanobis radius of the drawn surface.

Per-shape values (used where a per-element value is absent) go in a nested
``<bsdf type="lidar_material">`` with ``p_hit``, ``range_sigma`` and ``label``; analytic shapes
(spheres, cylinders, disks) carry their values there alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
from plyfile import PlyData, PlyElement

from mi_lidar.core.atomic import atomic_write, atomic_write_text
from mi_lidar.core.errors import ParameterError
from mi_lidar.scene.rebase import matrix_value

ELEMENT_ATTRIBUTES = ("p_hit", "range_sigma", "label", "reflectivity")
ANALYTIC_SHAPES = ("sphere", "cylinder", "disk")  # placed by their to_world alone; a cylinder loads as a mesh


def _element_columns(n: int, p_hit, range_sigma, label, reflectivity=None) -> list[tuple[str, np.ndarray]]:
    """Validated per-element attribute columns, in the fixed order of ELEMENT_ATTRIBUTES."""
    columns = []
    for name, values in zip(ELEMENT_ATTRIBUTES, (p_hit, range_sigma, label, reflectivity)):
        if values is None:
            continue
        values = np.broadcast_to(np.asarray(values, dtype=np.float32), (n,))
        if not np.all(np.isfinite(values)):
            raise ParameterError(f"{name} has non-finite values; give finite numbers per element")
        if name == "p_hit" and (values.min() < 0 or values.max() > 1):
            raise ParameterError(f"p_hit must lie in [0, 1]; got values in [{values.min():.3g}, {values.max():.3g}]")
        if name in ("range_sigma", "reflectivity") and values.min() < 0:
            raise ParameterError(f"{name} must be >= 0; got minimum {values.min():.3g}")
        columns.append((f"{name}_0", values))
    return columns


def write_mesh_ply(path, vertices, faces, p_hit=None, range_sigma=None, label=None, reflectivity=None) -> Path:
    """Write a triangle mesh with optional per-face element attributes as binary PLY.

    Args:
        path: output ``.ply``.
        vertices: (V, 3) positions, m.
        faces: (F, 3) vertex indices.
        p_hit, range_sigma, label, reflectivity: (F,) or scalar per-face values, or None to leave to
            the material.
    """
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise ParameterError(f"mesh needs (V, 3) vertices and (F, 3) faces; got {vertices.shape}, {faces.shape}")
    vert = np.empty(len(vertices), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vert["x"], vert["y"], vert["z"] = vertices.T
    columns = _element_columns(len(faces), p_hit, range_sigma, label, reflectivity)
    face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))] + [(n, "f4") for n, _ in columns])
    face["vertex_indices"] = faces
    for name, values in columns:
        face[name] = values
    ply = PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")], text=False)
    return atomic_write(path, ply.write)


def write_ellipsoids_ply(
    path, centers, scales, quaternions, p_hit=None, range_sigma=None, label=None, reflectivity=None
) -> Path:
    """Write an ellipsoid set in Mitsuba's ``ellipsoids`` PLY layout.

    Args:
        path: output ``.ply``.
        centers: (N, 3) Gaussian means, m.
        scales: (N, 3) standard deviations along the principal axes, m (> 0).
        quaternions: (N, 4) rotations to world in (x, y, z, w) order (real part last).
        p_hit, range_sigma, label, reflectivity: (N,) or scalar per-ellipsoid values, or None.
    """
    centers = np.asarray(centers, dtype=np.float32).reshape(-1, 3)
    scales = np.asarray(scales, dtype=np.float32).reshape(-1, 3)
    quaternions = np.asarray(quaternions, dtype=np.float32).reshape(-1, 4)
    n = len(centers)
    if len(scales) != n or len(quaternions) != n:
        raise ParameterError(
            f"ellipsoids need equal counts: {n} centers, {len(scales)} scales, {len(quaternions)} quaternions"
        )
    if n and scales.min() <= 0:
        raise ParameterError(f"ellipsoid scales must be > 0 m; got minimum {scales.min():.3g}")
    columns = _element_columns(n, p_hit, range_sigma, label, reflectivity)
    names = ["x", "y", "z", "nx", "ny", "nz"] + [c for c, _ in columns]
    names += ["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    rows = np.zeros(n, dtype=[(name, "f4") for name in names])
    rows["x"], rows["y"], rows["z"] = centers.T
    for name, values in columns:
        rows[name] = values
    log_scales = np.log(scales)
    for i in range(3):
        rows[f"scale_{i}"] = log_scales[:, i]
    norm = np.linalg.norm(quaternions, axis=1, keepdims=True)
    q = quaternions / np.where(norm > 0, norm, 1)
    rows["rot_0"], rows["rot_1"], rows["rot_2"], rows["rot_3"] = q[:, 3], q[:, 0], q[:, 1], q[:, 2]
    return atomic_write(path, PlyData([PlyElement.describe(rows, "vertex")], text=False).write)


@dataclass
class ShapeEntry:
    """One ``<shape>`` of a scene XML.

    Attributes:
        id: unique shape id.
        kind: ``"mesh"`` (a PLY triangle mesh), ``"ellipsoids"``, or one of :data:`ANALYTIC_SHAPES`
            (a Mitsuba analytic shape placed by ``to_world``).
        filename: PLY path, relative to the XML file (None for analytic shapes).
        p_hit, range_sigma, label: per-shape defaults written to a nested ``lidar_material``
            (None leaves Mitsuba's/sensor's default).
        extent: ellipsoid extent in sigmas (ellipsoids only).
        to_world: (4, 4) object-to-world matrix, m (analytic shapes; for files, None or the world
            position of the frame their coordinates are given in, e.g. a georeferenced local origin).
    """

    id: str
    kind: str
    filename: str | None = None
    p_hit: float | None = None
    range_sigma: float | None = None
    label: int | None = None
    extent: float | None = None
    to_world: np.ndarray | None = None


def shape_xml(entry: ShapeEntry, indent: str = "    ") -> str:
    """The ``<shape>`` element of ``entry`` as an XML string."""
    mitsuba_type = {"mesh": "ply", "ellipsoids": "ellipsoids"}.get(entry.kind)
    if mitsuba_type is None and entry.kind not in ANALYTIC_SHAPES:
        raise ParameterError(
            f"shape {entry.id!r}: kind {entry.kind!r} is not 'mesh', 'ellipsoids' or one of {ANALYTIC_SHAPES}"
        )
    lines = [f'{indent}<shape type="{mitsuba_type or entry.kind}" id={quoteattr(entry.id)}>']
    if mitsuba_type is not None:
        lines.append(f'{indent}    <string name="filename" value={quoteattr(entry.filename)}/>')
    if entry.to_world is not None:
        matrix = matrix_value(entry.to_world)
        lines.append(f'{indent}    <transform name="to_world"><matrix value="{matrix}"/></transform>')
    if entry.extent is not None:
        lines.append(f'{indent}    <float name="extent" value="{entry.extent:g}"/>')
    material = []
    if entry.p_hit is not None:
        material.append(f'<float name="p_hit" value="{entry.p_hit:.9g}"/>')
    if entry.range_sigma is not None:
        material.append(f'<float name="range_sigma" value="{entry.range_sigma:.9g}"/>')
    if entry.label is not None:
        material.append(f'<integer name="label" value="{int(entry.label)}"/>')
    if material:
        lines.append(f'{indent}    <bsdf type="lidar_material">')
        lines += [f"{indent}        {m}" for m in material]
        lines.append(f"{indent}    </bsdf>")
    lines.append(f"{indent}</shape>")
    return "\n".join(lines)


def write_scene_xml(path, shapes: list[ShapeEntry], header_comment: str = "", extra_xml: str = "") -> Path:
    """Write a Mitsuba scene XML listing ``shapes`` (plus raw ``extra_xml``, e.g. a sensor)."""
    ids = [s.id for s in shapes]
    duplicates = sorted({i for i in ids if ids.count(i) > 1})
    if duplicates:
        raise ParameterError(f"shape ids must be unique; repeated: {duplicates}")
    body = ['<?xml version="1.0" encoding="utf-8"?>']
    if header_comment:
        body.append(f"<!-- {header_comment} -->")
    body.append('<scene version="3.0.0">')
    body += [shape_xml(s) for s in shapes]
    if extra_xml:
        body.append(extra_xml)
    body.append("</scene>\n")
    return atomic_write_text(path, "\n".join(body))


def scene_with_effects(source: str | Path, effects: str, path: str | Path, density: str | None = None) -> Path:
    """Write a copy of the scene XML ``source`` whose ``lidar_integrator`` carries ``effects``, to ``path``.

    Used by ``diagnose`` to hand back the scene with the effects it found (the loop's next step is
    ``compare`` or ``calibrate`` on that file). The source's file references (``filename`` values, pattern
    tables, its density's ``file=`` tables) are made absolute, so the copy loads from any folder.

    Args:
        source: the scene XML.
        effects: the effects in the catalog's spec syntax, e.g. ``"range_bias(bias=0.02)"`` ("" for none).
        path: the output XML.
        density: a return density to set as well, e.g. ``"np_reg(file=np_reg.npz)"``, its file named relative
            to ``path``'s folder or absolute (None: the scene's stays).

    Raises:
        ParameterError: the scene has no ``<integrator type="lidar_integrator">``.
    """
    import re

    source = Path(source)
    text = source.read_text(encoding="utf-8")
    folder = source.resolve().parent

    def absolute(match: re.Match) -> str:
        value = match.group(2)
        return match.group(1) + quoteattr(str(folder / value)) if not Path(value).is_absolute() else match.group(0)

    text = re.sub(r'(name="filename"\s+value=)"([^"]+)"', absolute, text)
    text = re.sub(r'(name="pattern"\s+value=)"([^"]+\.(?:npy|csv|txt))"', absolute, text)

    def absolute_tables(match: re.Match) -> str:  # the file= arguments of a density spec
        def one(argument: re.Match) -> str:
            value = argument.group(2)
            return argument.group(1) + (value if Path(value).is_absolute() else str(folder / value))

        return match.group(1) + '"' + re.sub(r"(\bfile\s*=\s*)([^,)\s]+)", one, match.group(2)) + '"'

    text = re.sub(r'(name="density"\s+value=)"([^"]+)"', absolute_tables, text)
    settings = {"effects": effects} if density is None else {"effects": effects, "density": density}
    for name, value in settings.items():
        opening = re.search(r'<integrator\s+type="lidar_integrator"[^>]*?(/?)>', text)
        if opening is None:
            raise ParameterError(f'{source}: no <integrator type="lidar_integrator"> to carry the {name} {value!r}')
        line = f'<string name="{name}" value={quoteattr(value)}/>'
        existing = re.compile(rf'<string\s+name="{name}"\s+value="[^"]*"\s*/>')
        if opening.group(1):  # a self-closing integrator: open it
            head = opening.group(0)[:-2].rstrip()
            text = text[: opening.start()] + f"{head}>\n        {line}\n    </integrator>" + text[opening.end() :]
        else:
            close = text.index("</integrator>", opening.end())
            body = text[opening.end() : close]
            body = existing.sub(line, body) if existing.search(body) else f"\n        {line}" + body
            text = text[: opening.end()] + body + text[close:]
    return atomic_write_text(path, text)
