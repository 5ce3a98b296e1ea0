"""KITTI / nuScenes ``.bin`` point files: flat little-endian float32 records.

KITTI stores ``x y z intensity`` (4 columns); nuScenes ``LIDAR_TOP`` files store
``x y z intensity ring`` (5 columns). Coordinates are metres in the sensor frame.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import LogFormatError
from ._atomic import atomic_path


def write_kitti_bin(path: str | os.PathLike, points: np.ndarray, intensity: np.ndarray | None = None) -> Path:
    """Write (N, 4) float32 records ``x y z intensity``, atomically.

    Args:
        path: Destination ``.bin`` file.
        points: (N, 3) coordinates (m).
        intensity: (N,) intensities (sensor units, KITTI uses 0..1); zeros when None.

    Returns:
        The destination path.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"write_kitti_bin: points have shape {points.shape}; expected (N, 3)")
    records = np.zeros((len(points), 4), dtype="<f4")
    records[:, :3] = points
    if intensity is not None:
        intensity = np.asarray(intensity)
        if intensity.shape != (len(points),):
            raise ValueError(f"write_kitti_bin: intensity has shape {intensity.shape}; expected ({len(points)},)")
        records[:, 3] = intensity
    with atomic_path(path) as tmp:
        records.tofile(tmp)
    return Path(path)


def read_kitti_bin(path: str | os.PathLike, columns: int = 4) -> np.ndarray:
    """Read a KITTI (4 columns) or nuScenes (5 columns) ``.bin`` file.

    Args:
        path: A ``.bin`` file of float32 records.
        columns: Floats per record: 4 (x y z intensity) or 5 (x y z intensity ring).

    Returns:
        (N, columns) float32 array.

    Raises:
        LogFormatError: Missing file, or a size that is not a whole number of records.
    """
    if columns not in (4, 5):
        raise ValueError(f"read_kitti_bin: columns={columns}; expected 4 (KITTI) or 5 (nuScenes)")
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such .bin point file")
    size = path.stat().st_size
    record = 4 * columns
    if size % record:
        raise LogFormatError(
            f"{path}: {size} bytes is not a whole number of {columns}-float32 records ({record} bytes); "
            f"the file is truncated at byte {size - size % record} or has a different column count"
        )
    return np.fromfile(path, dtype="<f4").reshape(-1, columns).astype(np.float32)
