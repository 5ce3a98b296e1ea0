"""KITTI object-detection text files and SemanticKITTI point labels.

- ``calib/*.txt``: one ``KEY: v1 v2 ...`` line per matrix (``P0``..``Pn`` 3x4, ``R0_rect`` 3x3,
  ``Tr_velo_to_cam`` and ``Tr_imu_to_velo`` 3x4), row-major.
- ``label_2/*.txt``: one object per line: ``type truncated occluded alpha left top right bottom
  height width length x y z rotation_y`` (pixels, m, rad; x y z = bottom centre of the box in the
  reference camera frame, rotation_y about its y axis, 0 when the object's length runs along x).
- ``labels/*.label`` (SemanticKITTI): one little-endian uint32 per point of the matching ``.bin``,
  semantic id in the lower 16 bits, instance id in the upper 16.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path, atomic_write_text
from mi_lidar.core.errors import LogFormatError

LABEL_FIELDS = (
    "type",
    "truncated",
    "occluded",
    "alpha",
    "left",
    "top",
    "right",
    "bottom",
    "height",
    "width",
    "length",
    "x",
    "y",
    "z",
    "rotation_y",
)


def write_kitti_calib(path: str | os.PathLike, matrices: dict[str, np.ndarray]) -> Path:
    """Write calibration matrices as ``KEY: values`` lines (row-major, ``%.12e``), atomically."""
    text = "".join(f"{key}: {' '.join(f'{v:.12e}' for v in np.ravel(value))}\n" for key, value in matrices.items())
    return atomic_write_text(path, text)


def read_kitti_calib(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Matrices of a KITTI calibration file: 12 values -> (3, 4), 9 -> (3, 3).

    Raises:
        LogFormatError: missing file, or a line that is not ``KEY: numbers``.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such calibration file")
    matrices = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        key, sep, values = line.partition(":")
        try:
            numbers = np.array([float(v) for v in values.split()])
        except ValueError as exc:
            raise LogFormatError(f"{path}: line {number}: {exc}; expected 'KEY: numbers'") from exc
        if not sep or numbers.size not in (9, 12):
            raise LogFormatError(f"{path}: line {number} is not 'KEY: 9 or 12 numbers': {line[:60]!r}")
        matrices[key.strip()] = numbers.reshape(3, -1)
    return matrices


def write_kitti_labels(path: str | os.PathLike, objects: list[dict]) -> Path:
    """Write one ``label_2`` line per object (a dict with the keys of :data:`LABEL_FIELDS`), atomically."""
    lines = []
    for obj in objects:
        values = [str(obj["type"]), f"{obj['truncated']:.2f}", str(int(obj["occluded"]))]
        values += [f"{obj[k]:.2f}" for k in LABEL_FIELDS[3:]]
        lines.append(" ".join(values) + "\n")
    return atomic_write_text(path, "".join(lines))


def read_kitti_labels(path: str | os.PathLike) -> list[dict]:
    """Objects of a ``label_2`` file as dicts keyed by :data:`LABEL_FIELDS` (numbers as floats).

    Raises:
        LogFormatError: missing file, or a line with fewer than 15 fields.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such label file")
    objects = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 15:
            raise LogFormatError(f"{path}: line {number} has {len(fields)} fields; a KITTI label line has 15")
        obj: dict = {"type": fields[0]}
        obj.update({k: float(v) for k, v in zip(LABEL_FIELDS[1:], fields[1:15])})
        obj["occluded"] = int(obj["occluded"])
        objects.append(obj)
    return objects


def write_semantic_labels(path: str | os.PathLike, semantic: np.ndarray, instance: np.ndarray) -> Path:
    """Write SemanticKITTI labels: (N,) semantic ids and (N,) instance ids, each < 65536, atomically."""
    semantic, instance = np.asarray(semantic), np.asarray(instance)
    if semantic.shape != instance.shape or semantic.ndim != 1:
        raise ValueError(f"write_semantic_labels: shapes {semantic.shape} and {instance.shape}; expected equal (N,)")
    if len(semantic) and (
        semantic.min() < 0 or semantic.max() > 0xFFFF or instance.min() < 0 or instance.max() > 0xFFFF
    ):
        raise ValueError("write_semantic_labels: semantic and instance ids must lie in 0..65535")
    packed = (instance.astype("<u4") << 16) | semantic.astype("<u4")
    with atomic_path(path) as tmp:
        packed.astype("<u4").tofile(tmp)
    return Path(path)


def read_semantic_labels(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(N,) semantic and (N,) instance ids (uint16) of a SemanticKITTI ``.label`` file."""
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such label file")
    if path.stat().st_size % 4:
        raise LogFormatError(f"{path}: {path.stat().st_size} bytes is not a whole number of uint32 labels")
    packed = np.fromfile(path, dtype="<u4")
    return (packed & 0xFFFF).astype(np.uint16), (packed >> 16).astype(np.uint16)
