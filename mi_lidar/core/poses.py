"""Sensor poses: validation of (S, 4, 4) sensor-to-world rigid transforms."""

from __future__ import annotations

import os

import numpy as np

from mi_lidar.core.errors import PoseError
from mi_lidar.core.frames import MAX_COORDINATE_M

RIGID_TOLERANCE = 1e-4


def validate_poses(poses: np.ndarray, source: str | os.PathLike = "poses") -> np.ndarray:
    """Check that every pose is a finite rigid transform at a position on Earth.

    Args:
        poses: (S, 4, 4) or (4, 4) sensor-to-world transforms.
        source: Name used in error messages (usually the file).

    Returns:
        ``poses`` as (S, 4, 4) float64.

    Raises:
        PoseError: Naming ``source``, the first bad pose index and what is wrong: non-finite
            entries, ``R^T R != I`` or ``det(R) != 1`` beyond 1e-4, a last row other than
            ``0 0 0 1``, or a position beyond :data:`~mi_lidar.core.frames.MAX_COORDINATE_M`.
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
    far = np.abs(poses[:, :3, 3]) > MAX_COORDINATE_M
    if far.any():
        pose, axis = (int(k) for k in np.unravel_index(int(np.argmax(far)), far.shape))
        raise PoseError(
            f"{source}: pose {pose} has position {'xyz'[axis]} = {poses[pose, axis, 3]:.3g} m, beyond "
            f"{MAX_COORDINATE_M:.0e} m (farther than any Earth-fixed coordinate): a misread number; repair the pose"
        )
    return poses
