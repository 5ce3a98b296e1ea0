"""Sensor pose files: KITTI odometry pose text files and generic 4x4 matrix files.

A KITTI pose file has one pose per line: 12 numbers, the row-major top 3x4 of a 4x4
sensor-to-world transform. A matrix file is an ``.npy`` of shape (S, 4, 4) or a text file with 16
numbers per line (row-major 4x4). Every pose read is validated as a rigid transform.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import LogFormatError, PoseError
from ..atomic import atomic_path

RIGID_TOLERANCE = 1e-4


def validate_poses(poses: np.ndarray, source: str | os.PathLike = "poses") -> np.ndarray:
    """Check that every pose is a finite rigid transform.

    Args:
        poses: (S, 4, 4) or (4, 4) sensor-to-world transforms.
        source: Name used in error messages (usually the file).

    Returns:
        ``poses`` as (S, 4, 4) float64.

    Raises:
        PoseError: Naming ``source``, the first bad pose index and what is wrong: non-finite
            entries, ``R^T R != I`` or ``det(R) != 1`` beyond 1e-4, or a last row other than
            ``0 0 0 1``.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape == (4, 4):
        poses = poses[None]
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise PoseError(f"{source}: poses have shape {poses.shape}; expected (S, 4, 4)")
    if len(poses) == 0:
        raise PoseError(f"{source}: no poses; give at least one 4x4 matrix")
    finite = np.isfinite(poses).all(axis=(1, 2))
    rot = np.where(finite[:, None, None], poses[:, :3, :3], np.eye(3))
    orth = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    last = np.abs(np.where(finite[:, None], poses[:, 3], 0.0) - [0, 0, 0, 1]).max(axis=1)
    checks = (
        (~finite, lambda i: "has non-finite entries"),
        (orth > RIGID_TOLERANCE, lambda i: f"rotation is not orthonormal (max |R^T R - I| = {orth[i]:.3g})"),
        (np.abs(det - 1) > RIGID_TOLERANCE, lambda i: f"rotation determinant is {det[i]:.6g}; expected 1"),
        (last > RIGID_TOLERANCE, lambda i: f"last row is {poses[i, 3].tolist()}; expected [0, 0, 0, 1]"),
    )
    for bad, describe in checks:
        if bad.any():
            i = int(np.argmax(bad))
            raise PoseError(f"{source}: pose {i} is not a rigid transform: {describe(i)}")
    return poses


def _read_text_rows(path: Path, width: int) -> np.ndarray:
    """Rows of ``width`` numbers from a whitespace-separated text file (blank lines skipped)."""
    rows = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) != width:
                raise LogFormatError(f"{path}: line {number} has {len(fields)} numbers; expected {width}")
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


def write_kitti_poses(path: str | os.PathLike, poses: np.ndarray) -> Path:
    """Write (S, 4, 4) rigid transforms as a KITTI pose file (12 numbers per line), atomically.

    Raises:
        PoseError: A pose is not a finite rigid transform.
    """
    poses = validate_poses(poses, path)
    with atomic_path(path) as tmp:
        np.savetxt(tmp, poses[:, :3, :].reshape(-1, 12), fmt="%.9e")
    return Path(path)


def read_pose_matrices(path: str | os.PathLike) -> np.ndarray:
    """Read 4x4 pose matrices from an ``.npy`` file ((S, 4, 4)) or a text file (16 numbers per line).

    Returns:
        (S, 4, 4) float64 sensor-to-world transforms.

    Raises:
        LogFormatError: Missing or unreadable file, or wrong shape.
        PoseError: A pose that is not a finite rigid transform.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such pose file")
    if path.suffix.lower() == ".npy":
        try:
            poses = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise LogFormatError(f"{path}: not a readable .npy array ({exc})") from exc
        if poses.ndim == 2 and poses.shape == (4, 4):
            poses = poses[None]
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise LogFormatError(f"{path}: array has shape {poses.shape}; expected (S, 4, 4)")
    else:
        poses = _read_text_rows(path, 16).reshape(-1, 4, 4)
    return validate_poses(poses, path)
