"""Sensor pose files: KITTI odometry pose text files and generic 4x4 matrix files.

A KITTI pose file has one pose per line: 12 numbers, the row-major top 3x4 of a 4x4
sensor-to-world transform. A matrix file is an ``.npy`` of shape (S, 4, 4) or a text file with 16
numbers per line (row-major 4x4). Text lines starting with ``#`` are comments. :func:`read_poses`
reads any of them, or the poses of a saved log (``.npz``). Every pose read is validated as a rigid
transform.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import NUMPY_FILE_ERRORS, LogFormatError, unreadable
from mi_lidar.core.poses import validate_poses
from mi_lidar.io.signature import check_signature, read_head, sniff

TEXT_RESOLUTION_M = 1e-6  # finest step a written position keeps (m)


COMMENT = "#"  # a line starting with it is a comment (a header some tools write)


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith(COMMENT)


def _read_text_rows(path: Path, width: int) -> np.ndarray:
    """Rows of ``width`` numbers from a whitespace-separated text file (blank and ``#`` comment lines skipped)."""
    rows = []
    try:
        stream = open(path, encoding="utf-8", errors="replace")
    except PermissionError as exc:
        raise unreadable(path) from exc
    with stream:
        for number, line in enumerate(stream, start=1):
            fields = line.split()
            if not fields or _is_comment(line):
                continue
            if len(fields) != width:
                if "," in line:
                    raise LogFormatError(
                        f"{path}: line {number}: numbers separated by commas; pose files separate them by spaces: "
                        "replace the commas by spaces"
                    )
                cut = " (the file is cut short?)" if not line.endswith("\n") else ""
                raise LogFormatError(
                    f"{path}: line {number} has {len(fields)} numbers; expected {width}{cut}: repair or delete the line"
                )
            try:
                rows.append([float(f) for f in fields])
            except ValueError as exc:
                raise LogFormatError(f"{path}: line {number}: {exc}; expected {width} numbers") from exc
    if not rows:
        raise LogFormatError(f"{path}: no poses found; expected lines of {width} numbers")
    return np.array(rows, dtype=np.float64)


def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI odometry pose file.

    Args:
        path: Text file, one pose per line: 12 numbers = row-major 3x4 ``[R | t]`` (t in m).

    Returns:
        (S, 4, 4) float64 sensor-to-world transforms.

    Raises:
        LogFormatError: Missing file, or a line without exactly 12 numbers.
        PoseError: A pose that is not a finite rigid transform.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such pose file")
    rows = _read_text_rows(path, 12)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return validate_poses(poses, path)


POSE_FILES = ".npy (S, 4, 4), a saved log (.npz: its poses), or text with 12 (KITTI) or 16 numbers per line"


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """Sensor poses from any pose file: see :data:`POSE_FILES` (the text kind from its first line).

    Returns:
        (S, 4, 4) float64 sensor-to-world transforms.

    Raises:
        LogFormatError: a missing file, a binary file that is none of these, or a malformed one.
        PoseError: a pose that is not a finite rigid transform.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such pose file; give {POSE_FILES}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        return read_pose_matrices(path)
    if suffix == ".npz":
        from mi_lidar.core.log import Log

        check_signature(path, "npz")
        return validate_poses(Log.load(path).poses, path)
    head = read_head(path, 4096)
    found = sniff(head)
    if found is not None or b"\0" in head:
        raise LogFormatError(
            f"{path}: {found[0].kind if found else 'a binary file'}, not a pose file; give {POSE_FILES}"
        )
    lines = head.decode("utf-8", "replace").splitlines()
    data = ((i, line) for i, line in enumerate(lines, start=1) if line.strip() and not _is_comment(line))
    number, first = next(data, (0, ""))
    width = len(first.split())
    if width and width not in (12, 16) and "," not in first:
        raise LogFormatError(
            f"{path}: line {number} has {width} numbers; a pose file has 12 (KITTI: a 3x4 [R | t]) or 16 (a 4x4 "
            "matrix) on each line: repair or delete the line"
        )
    return read_kitti_poses(path) if width == 12 else read_pose_matrices(path)


def write_kitti_poses(path: str | os.PathLike, poses: np.ndarray) -> Path:
    """Write (S, 4, 4) rigid transforms as a KITTI pose file (12 numbers per line), atomically.

    Numbers carry 10 significant digits (``%.9e``), more where positions are georeferenced, so that
    every position keeps :data:`TEXT_RESOLUTION_M` (4,000,000 m needs 13 digits).

    Raises:
        PoseError: A pose is not a finite rigid transform.
    """
    poses = validate_poses(poses, path)
    largest = float(np.abs(poses[:, :3, 3]).max())
    digits = max(9, int(np.ceil(np.log10(max(largest, 1.0) / TEXT_RESOLUTION_M))))
    with atomic_path(path) as tmp:
        np.savetxt(tmp, poses[:, :3, :].reshape(-1, 12), fmt=f"%.{digits}e")
    return Path(path)


def read_pose_matrices(path: str | os.PathLike) -> np.ndarray:
    """Read 4x4 pose matrices from an ``.npy`` file ((S, 4, 4)) or a text file (16 numbers per line).

    Returns:
        (S, 4, 4) float64 sensor-to-world transforms.

    Raises:
        LogFormatError: Missing or unreadable file (an ``.npy`` that is empty, another format or damaged), values
            that are not real numbers, or a wrong shape.
        PoseError: A pose that is not a finite rigid transform.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such pose file")
    if path.suffix.lower() == ".npy":
        check_signature(path, "npy")
        try:
            poses = np.load(path, allow_pickle=False)
        except NUMPY_FILE_ERRORS as exc:
            raise LogFormatError(f"{path}: not a readable .npy array ({type(exc).__name__}: {exc})") from exc
        if poses.dtype.kind not in "iuf":
            raise LogFormatError(f"{path}: array of {poses.dtype} values; expected real numbers (float64 poses)")
        if poses.ndim == 2 and poses.shape == (4, 4):
            poses = poses[None]
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise LogFormatError(f"{path}: array has shape {poses.shape}; expected (S, 4, 4)")
    else:
        poses = _read_text_rows(path, 16).reshape(-1, 4, 4)
    return validate_poses(poses, path)
