"""KITTI / nuScenes ``.bin`` point files: flat little-endian float32 records.

KITTI stores ``x y z intensity`` (4 columns); nuScenes ``LIDAR_TOP`` files store
``x y z intensity ring`` (5 columns). Coordinates are metres in the sensor frame. The format has no
header: a file cut at a record boundary reads as a smaller scan (a cut inside a record, a size of the
wrong record length, or bytes that are not such records are refused).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.core.frames import check_float32
from mi_lidar.core.log import Log
from mi_lidar.io.cloud import check_coordinates, cloud_from_log, log_from_points


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
        LogFormatError: Missing or unreadable file, a size that is not a whole number of records, or only
            zero bytes.
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
    try:
        records = np.fromfile(path, dtype="<f4").reshape(-1, columns).astype(np.float32)
    except PermissionError as exc:
        raise unreadable(path) from exc
    if size and not records.view(np.uint32).any():  # (integers: a signalling NaN in random bytes warns)
        raise LogFormatError(
            f"{path}: all {size} bytes are zero, no point data (a file allocated but never written?); re-create or "
            "copy it again"
        )
    return records


NUSCENES_MIN_RANGE = 1.0


def read_bin_log(path: str | os.PathLike, columns: int | None = None, min_range: float | None = None) -> Log:
    """Read a KITTI or nuScenes ``.bin`` scan as a one-scan log.

    Args:
        path: The ``.bin`` file.
        columns: 4 (KITTI) or 5 (nuScenes, with ring ids); guessed when None: 5 for names ending
            in ``.pcd.bin`` or sizes that only divide into 20-byte records, else 4.
        min_range: Points closer than this are misses (m); default 1.0 for nuScenes (its near-origin
            points are ego-vehicle hits and no-return placeholders), 0 for KITTI.

    Returns:
        KITTI: ``H = 1``, ``W = N`` in file order. nuScenes: one row per ring (highest on top),
        columns in firing order. ``attributes['intensity']`` holds the intensity column.

    Raises:
        LogFormatError: As :func:`read_kitti_bin`, a coordinate beyond :data:`~mi_lidar.core.frames.MAX_COORDINATE_M`
            (the bytes are not such records), or ring ids that are not small integers.
    """
    path = Path(path)
    if columns is None:
        size = path.stat().st_size if path.is_file() else 0
        nuscenes = path.name.endswith(".pcd.bin") or (size % 20 == 0 and size % 16 != 0)
        columns = 5 if nuscenes else 4
    records = read_kitti_bin(path, columns)
    check_coordinates(
        records[:, :3],
        path,
        f"not {columns}-column float32 records (another format, another column count: columns=, or a damaged file)",
    )
    if min_range is None:
        min_range = NUSCENES_MIN_RANGE if columns == 5 else 0.0
    ring = None
    if columns == 5:
        ring = records[:, 4]
        bad = ~((ring == np.round(ring)) & (ring >= 0) & (ring < 1024))
        if bad.any():
            index = int(np.argmax(bad))
            raise LogFormatError(
                f"{path}: point {index} has ring (column 5) {ring[index]:g}; ring ids are integers 0..1023: not a "
                "nuScenes scan (a KITTI file: columns=4), or a damaged file"
            )
    return log_from_points(
        records[:, :3],
        {"intensity": records[:, 3]},
        ring=ring,
        min_range=min_range,
        sensor={"name": "nuscenes" if columns == 5 else "kitti", "source": str(path), "min_range_m": min_range},
    )


def write_bin_log(log: Log, path: str | os.PathLike, scan: int = 0) -> Path:
    """Write the hits of one scan as a KITTI ``.bin`` (x y z intensity; misses cannot be stored).

    Raises:
        LogFormatError: the points are georeferenced world coordinates (a cloud read at a local origin)
            that float32 keeps more coarsely than 1 mm.
    """
    cloud = cloud_from_log(log, scan)
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    check_float32(
        points,
        str(path),
        "KITTI .bin stores float32 and the points",
        "Write .las, .ply or .pcd, which keep float64 coordinates",
        LogFormatError,
    )
    return write_kitti_bin(path, points, cloud["intensity"])
