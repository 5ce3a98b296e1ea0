"""Annotations and scene composition (thesis fig. 4.13).

An annotation is JSON::

    {"format": "mi-lidar-annotation", "version": 1,
     "ground": "ground.ply",                      # optional triangle mesh, relative to the file
     "objects": [{"class": "small_tree", "center": [x, y, z], "yaw": 0.3,
                  "extents": [lx, ly, lz]}, ...],  # m, rad; center = object centroid
     "sensor": {"pattern": "pattern.npy",         # optional: pattern table (relative) or name,
                "poses": [[16 floats], ...],      # row-major sensor-to-world poses along the path,
                "min_range": 1.0, "max_range": 80.0}}  # m

A scene is the ground plus, per object, the library primitive of the same class whose box
extents are closest, rotated by ``yaw`` about z and moved to ``center``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, PositiveFloat, ValidationError, field_validator

from mi_lidar.core.errors import PoseError, SceneError, describe_invalid
from mi_lidar.core.log import Log
from mi_lidar.core.patterns import to_table
from mi_lidar.core.patterns.from_log import pattern_from_log
from mi_lidar.core.poses import validate_poses
from mi_lidar.core.strict_json import write_json
from mi_lidar.hybrid.blocks import SceneSensor, read_mesh_ply
from mi_lidar.hybrid.classes import CLASS_NAMES, class_id
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh, HybridModel
from mi_lidar.hybrid.primitives import PrimitiveLibrary, object_pose, oriented_box, rotation_z, sensor_velocity_at
from mi_lidar.hybrid.segments import Segment
from mi_lidar.scene.files import write_mesh_ply


def annotation_from_segments(points: np.ndarray, segments: list[Segment], poses: np.ndarray) -> list[dict]:
    """Annotation objects (class, centroid, yaw, box extents) of labelled segments.

    Args:
        points: (N, 3) m. segments: labelled segments. poses: (S, 4, 4) sensor poses.
    """
    objects = []
    for seg in segments:
        pts = points[seg.index]
        center, yaw = object_pose(pts, sensor_velocity_at(poses, pts[:, :2].mean(axis=0)))
        lo, hi = oriented_box(pts, center, yaw)
        objects.append(
            {
                "class": CLASS_NAMES[seg.label],
                "center": [float(x) for x in center],
                "yaw": yaw,
                "extents": [float(x) for x in hi - lo],
                "segment": int(seg.id),
            }
        )
    return objects


def save_annotation(path, objects: list[dict], ground: GroundMesh | None = None, log: Log | None = None) -> list[Path]:
    """Write an annotation JSON and the files it names beside it.

    Args:
        path: output ``.json``.
        objects: annotation objects.
        ground: ground mesh, written to ``<stem>_ground.ply`` (None: no ground).
        log: the log the annotation came from; its scan-0 firing pattern (``<stem>_pattern.npy``),
            poses and range limits become the annotation's ``sensor`` (None: no sensor).

    Returns:
        The paths written: the JSON first, then the ground mesh and the pattern table when written
        (``annotation, *files = save_annotation(...)``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"format": "mi-lidar-annotation", "version": 1, "objects": objects}
    written = []
    if ground is not None:
        name = f"{path.stem}_ground.ply"
        written.append(
            write_mesh_ply(
                path.parent / name, ground.vertices, ground.faces, ground.p_hit, ground.range_sigma, ground.label
            )
        )
        doc["ground"] = name
    if log is not None:
        table = to_table(pattern_from_log(log), path.parent / f"{path.stem}_pattern.npy")
        written.append(table)
        doc["sensor"] = {
            "pattern": table.name,
            "poses": log.poses.reshape(-1, 16).tolist(),
            "min_range": float(log.sensor.get("min_range", 0.0)),
            "max_range": float(log.sensor.get("max_range", 120.0)),
        }
    return [write_json(path, doc), *written]


class _AnnotationPart(BaseModel):
    """A part of an annotation file: NaN and infinite numbers are errors; keys of other tools are kept."""

    model_config = ConfigDict(extra="allow", allow_inf_nan=False)


class AnnotatedObject(_AnnotationPart):
    """One object: its class, centroid (m), heading (rad) and box extents (m)."""

    class_name: str = Field(alias="class")
    center: tuple[float, float, float]
    yaw: float
    extents: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat]

    @field_validator("class_name")
    @classmethod
    def _known(cls, value):
        class_id(value)
        return value


class AnnotatedSensor(_AnnotationPart):
    """The sensor of the log an annotation came from: pattern, row-major 4x4 poses, range limits (m)."""

    pattern: str
    poses: list[tuple[float, ...]] = Field([tuple(np.eye(4).ravel())], min_length=1)
    min_range: NonNegativeFloat = 0.0
    max_range: PositiveFloat = 120.0

    @field_validator("poses")
    @classmethod
    def _sixteen(cls, value):
        for i, pose in enumerate(value):
            if len(pose) != 16:
                raise ValueError(f"pose {i} has {len(pose)} numbers; give the 16 of a row-major 4x4 matrix")
        return value


class AnnotationFile(_AnnotationPart):
    """A whole annotation file (see the module docstring)."""

    format: Literal["mi-lidar-annotation"]
    version: Literal[1] = 1
    ground: str | None = None
    objects: list[AnnotatedObject] = []
    sensor: AnnotatedSensor | None = None


def read_annotation(path) -> AnnotationFile:
    """The validated contents of an annotation file.

    Raises:
        SceneError: the file is missing, unreadable, not JSON, or any field is invalid (every one is
            listed with its place, e.g. ``objects.3.center``).
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: no such annotation file")
    try:
        doc = json.loads(path.read_text())
    except UnicodeDecodeError:
        raise SceneError(
            f"{path}: a binary file, not an annotation: an annotation is a JSON text file (class, pose and box per "
            "object), e.g. from `mi-lidar annotate LOG.npz --out annotation.json`; see docs/hybrid_scenes.md "
            "(Annotation files)"
        ) from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read the annotation: {exc}") from None
    except json.JSONDecodeError as exc:
        raise SceneError(
            f"{path}: not JSON ({exc}); see docs/hybrid_scenes.md (Annotation files) for the format"
        ) from None
    try:
        return AnnotationFile.model_validate(doc)
    except ValidationError as exc:
        header = f"{path}: invalid annotation:"
        raise SceneError(
            describe_invalid(exc.errors(), header, "See docs/hybrid_scenes.md (Annotation files) for the format.")
        ) from None


def load_annotation(path) -> tuple[list[dict], GroundMesh | None]:
    """Objects (dicts with ``class``, ``center``, ``yaw``, ``extents``) and optional ground mesh of an annotation.

    Raises:
        SceneError: as :func:`read_annotation`, or the ground mesh cannot be read.
    """
    path = Path(path)
    annotation = read_annotation(path)
    objects = [obj.model_dump(by_alias=True) for obj in annotation.objects]
    try:
        ground = read_mesh_ply(path.parent / annotation.ground) if annotation.ground else None
    except SceneError as exc:
        raise SceneError(f"{path}: ground: {exc}") from None
    return objects, ground


def annotation_sensor(path) -> tuple[SceneSensor, np.ndarray] | None:
    """The sensor stored in an annotation file and its (S, 4, 4) poses, or None if it has none.

    The sensor sits at the first pose; a pattern given as a file is resolved next to the annotation.

    Raises:
        SceneError: as :func:`read_annotation`, or a pose is not a rigid transform.
    """
    path = Path(path)
    info = read_annotation(path).sensor
    if info is None:
        return None
    try:
        poses = validate_poses(np.asarray(info.poses, float).reshape(-1, 4, 4), f"{path}: sensor.poses")
    except PoseError as exc:
        raise SceneError(str(exc)) from None
    pattern = info.pattern
    if Path(pattern).suffix.lower() in (".npy", ".csv", ".json"):
        pattern = str((path.parent / pattern).resolve())
    return SceneSensor(pattern, poses[0], info.min_range, info.max_range), poses


def compose_scene(
    objects: list[dict],
    library: PrimitiveLibrary,
    ground: GroundMesh | None = None,
    extent: float = 3.5,
    missing: str = "skip",
) -> HybridModel:
    """Build a scene from annotation objects and a primitive library.

    Args:
        objects: annotation objects (see module docstring).
        library: primitives.
        ground: ground mesh (None: no ground).
        extent: ellipsoid extent, sigmas.
        missing: ``"skip"`` leaves out objects whose class the library lacks (their indices are
            listed in ``info["skipped"]``); ``"error"`` raises :class:`SceneError`.

    Returns:
        The model; ellipsoids carry their object's index + 1 as ``instance`` and sit in block 0.
    """
    if missing not in ("skip", "error"):
        raise SceneError(f"missing={missing!r}; choose 'skip' or 'error'")
    parts, skipped = [], []
    for i, obj in enumerate(objects):
        if missing == "skip" and not library.of_class(obj["class"]):
            skipped.append(i)
            continue
        prim = library.best_match(obj["class"], obj["extents"])
        ell = prim.ellipsoids.transformed(rotation_z(float(obj["yaw"])), np.asarray(obj["center"], float))
        ell.instance[:] = i + 1
        parts.append(ell)
    ground = ground if ground is not None else GroundMesh(np.zeros((0, 3)), np.zeros((0, 3)))
    return HybridModel(ground, EllipsoidSet.concat(parts), extent, info={"n_objects": len(objects), "skipped": skipped})
