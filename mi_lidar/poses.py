"""Sensor poses: validation of 4x4 rigid transforms."""

from __future__ import annotations

import numpy as np

from .errors import PoseError

RIGID_TOLERANCE = 1e-4


def validate_poses(poses, source: str = "poses") -> np.ndarray:
    """Return ``poses`` as a (S, 4, 4) float64 array of rigid transforms or raise PoseError.

    Args:
        poses: (4, 4) or (S, 4, 4) sensor-to-world transforms.
        source: name used in error messages (a file name, for example).
    """
    array = np.asarray(poses, dtype=np.float64)
    if array.shape == (4, 4):
        array = array[None]
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise PoseError(f"{source}: expected (S, 4, 4) pose matrices; got shape {array.shape}")
    if len(array) == 0:
        raise PoseError(f"{source}: no poses; give at least one 4x4 matrix")
    for i, pose in enumerate(array):
        if not np.all(np.isfinite(pose)):
            raise PoseError(f"{source}: pose {i} has non-finite entries (NaN or inf); fix or drop it")
        rotation = pose[:3, :3]
        if not np.allclose(pose[3], [0, 0, 0, 1], atol=RIGID_TOLERANCE):
            raise PoseError(f"{source}: pose {i} has last row {pose[3].tolist()}; a rigid transform ends in [0, 0, 0, 1]")
        error = np.abs(rotation.T @ rotation - np.eye(3)).max()
        if error > RIGID_TOLERANCE or np.linalg.det(rotation) < 0:
            raise PoseError(
                f"{source}: pose {i} is not rigid (|R^T R - I| = {error:.2g}, det R = {np.linalg.det(rotation):.4f}); "
                "give a rotation without scale or shear"
            )
    return array
