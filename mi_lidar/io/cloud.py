"""Conversions between point clouds and :class:`~mi_lidar.core.log.Log` range images.

Point-cloud formats (KITTI/nuScenes ``.bin``, PLY, PCD, LAS, ROS ``PointCloud2``) carry points,
not rays. :func:`log_from_points` rebuilds the ray grid:

- with a ``ring`` field: one row per ring id, highest-elevation ring on top (rows are flipped when
  the median elevation grows with the ring id, the Velodyne/ROS convention); within a ring the
  column is the ``column`` field when present, otherwise the point's order of appearance (the
  firing order for nuScenes and Velodyne drivers). Grid cells no point fills have
  ``attributes['valid']`` False;
- without a ring field: one row, ``H = 1`` and ``W = N``, in file order.

The rays start at the sensor's origin, or at the per-point ``origin_x origin_y origin_z`` fields
(m, sensor frame) when a cloud has them (:data:`ORIGIN_FIELDS`, written by the ROS 2 bag writer for
logs with non-zero ray origins); the range is the point's distance from its ray's origin and its
direction the unit vector from there to it. Points that are not finite or closer than
``min_range`` are misses (``hit`` False, range NaN) kept in the grid, never dropped. A miss has no
trustworthy direction, so it gets the estimated pattern direction: its row's median elevation and
its column's mean azimuth (columns without any return are interpolated from their neighbours).

A cloud read without a pose is in world coordinates; a georeferenced one (UTM, say: most points far
from the origin, :func:`georeferenced`) is read at a local origin, the rounded centre of its bounding
box, which becomes the scan's pose, so that the log's float32 ranges keep 0.1 mm
(:mod:`mi_lidar.core.frames`).

:func:`cloud_from_log` goes the other way and defines the standard fields every writer uses:
``x y z`` (float32, m, sensor frame; float64 world coordinates for a cloud read at a local
origin), ``intensity`` (float32, from the ``intensity``,
``reflectivity`` or ``signal`` attribute, else 0), ``ring`` (uint16, ``H - 1 - row``: ring 0 is
the lowest beam), ``column`` (uint32) and ``time`` (float32, s since the scan's first ray).
"""

from __future__ import annotations

import warnings

import numpy as np

from mi_lidar.core.errors import CoarseCoordinatesWarning, LogFormatError
from mi_lidar.core.frames import MAX_COORDINATE_M, NEAR_M, float32_message, local_origin, needs_float64
from mi_lidar.core.log import Log

MAX_EMPTY_CELLS = 1 << 20  # a damaged ring or column field cannot make a huge grid (and a slow read)
INTENSITY_SOURCES = ("intensity", "reflectivity", "signal")
STANDARD_FIELDS = ("x", "y", "z", "intensity", "ring", "column", "time")
ORIGIN_FIELDS = ("origin_x", "origin_y", "origin_z")  # per-point ray origins (m, sensor frame), when not all zero
COARSE_FIX = (
    "The points are no finer than that: the file lost the precision when it was written. Export the cloud with "
    "double coordinates (PLY 'property double', PCD 'SIZE 8') or relative to a local origin."
)
CLOUD_ORIGIN = "cloud_origin"  # Log.sensor key: a world cloud read at this local origin (m), written back in world


def _grid_indices(
    count: int, ring: np.ndarray | None, column: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Row and column of each point, and the grid size ``(H, W)``."""
    if ring is None:
        return np.zeros(count, dtype=np.int64), np.arange(count), 1, max(count, 1)
    ring = np.asarray(ring).astype(np.int64)
    if column is None:
        order = np.argsort(ring, kind="stable")
        sorted_ring = ring[order]
        starts = np.searchsorted(sorted_ring, sorted_ring, side="left")
        column = np.empty(count, dtype=np.int64)
        column[order] = np.arange(count) - starts
    column = np.asarray(column).astype(np.int64)
    height = int(ring.max()) + 1 if count else 1
    width = int(column.max()) + 1 if count else 1
    return ring, column, height, width


def _fill_gaps(values: np.ndarray, known: np.ndarray, default: float) -> np.ndarray:
    """Linearly interpolate ``values`` where ``known`` is False (1-D)."""
    if not known.any():
        return np.full(values.shape, default)
    index = np.arange(len(values))
    return np.interp(index, index[known], values[known])


def estimated_directions(directions: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """(H, W, 3) pattern directions estimated from the hit rays of one scan.

    Row elevation = median elevation of the row's hits; column azimuth = circular mean of the
    column's hit azimuths after removing each row's median azimuth offset; rows and columns
    without hits are interpolated from their neighbours.
    """
    elevation = np.arcsin(np.clip(directions[..., 2], -1, 1))
    azimuth = np.arctan2(directions[..., 1], directions[..., 0])
    masked = np.where(hit, elevation, np.nan)
    row_known = hit.any(axis=1)
    row_elevation = _fill_gaps(np.nanmedian(np.where(row_known[:, None], masked, 0.0), axis=1), row_known, 0.0)
    unit = np.where(hit, np.exp(1j * azimuth), 0)
    column_known = hit.any(axis=0)
    column_mean = np.angle(unit.sum(axis=0))
    unwrapped = np.unwrap(np.where(column_known, column_mean, 0.0)[column_known]) if column_known.any() else np.zeros(0)
    filled = np.zeros(hit.shape[1])
    if column_known.any():
        filled[column_known] = unwrapped
        filled = _fill_gaps(filled, column_known, 0.0)
    row_offset = np.angle(np.where(hit, np.exp(1j * (azimuth - filled[None, :])), 0).sum(axis=1))
    alpha = filled[None, :] + row_offset[:, None]
    omega = np.broadcast_to(row_elevation[:, None], alpha.shape)
    return np.stack([np.cos(omega) * np.cos(alpha), np.cos(omega) * np.sin(alpha), np.sin(omega)], axis=-1)


def check_coordinates(
    points: np.ndarray, source, hint: str = "a damaged file, or a wrong scale or offset: export it again"
) -> None:
    """Refuse a cloud with a finite coordinate beyond :data:`MAX_COORDINATE_M` (non-finite points are misses).

    Args:
        points: (N, 3) coordinates (m).
        source: The file, named in the message.
        hint: What such a number says about the file, and what to do.

    Raises:
        LogFormatError: naming the first such point, its axis and value.
    """
    points = np.asarray(points)
    bad = np.abs(np.where(np.isfinite(points), points, 0.0)) > MAX_COORDINATE_M
    if bad.any():
        index, axis = np.unravel_index(int(np.argmax(bad)), bad.shape)
        raise LogFormatError(
            f"{source}: point {index} has {'xyz'[axis]} = {points[index, axis]:.3g} m, beyond {MAX_COORDINATE_M:.0e} "
            f"m: {hint}"
        )


def georeferenced(points: np.ndarray) -> bool:
    """Whether a cloud's (N, 3) finite points are georeferenced: most of them (the median point's largest
    coordinate) lie beyond :data:`~mi_lidar.core.frames.NEAR_M` from the origin. A scan in its sensor's frame
    surrounds the origin: a few stray far points (a damaged reading) do not move its sensor to the centre of their
    bounding box."""
    return bool(len(points)) and float(np.median(np.abs(points).max(axis=1))) > NEAR_M


def _check_index_field(values: np.ndarray, name: str, source, limit: int) -> None:
    """Refuse a ring or column field that is not made of non-negative integers below ``limit`` (a larger one
    makes a grid larger than :func:`log_from_points` takes, and one beyond int64 wraps to a negative index).

    Raises:
        LogFormatError: naming the field, the first bad point and its value.
    """
    bad = ~(np.isfinite(values) & (values >= 0) & (values == np.round(values)))
    if bad.any():
        i = int(np.argmax(bad))
        raise LogFormatError(f"{source}: field {name!r} must hold non-negative integers; point {i} has {values[i]}")
    if values.max() >= limit:
        i = int(np.argmax(values))
        raise LogFormatError(
            f"{source}: field {name!r} of point {i} is {values[i]:.6g}; ring and column indices of {len(values):,} "
            f"points stay below {limit:,} (a grid that large is mostly empty): a damaged field; export the file again"
        )


def log_from_points(
    points: np.ndarray,
    attributes: dict[str, np.ndarray] | None = None,
    ring: np.ndarray | None = None,
    column: np.ndarray | None = None,
    times: np.ndarray | None = None,
    min_range: float = 0.0,
    sensor: dict | None = None,
    pose: np.ndarray | None = None,
    origins: np.ndarray | None = None,
) -> Log:
    """Build a one-scan log from a point cloud (see the module docstring for the layout).

    Args:
        points: (N, 3) points (m) in the sensor frame.
        attributes: Name -> (N,) per-point values, copied into the grid (0 where no point); a
            ``valid`` attribute (a cloud written from a log) marks its False points invalid as well.
        ring: Optional (N,) ring ids (non-negative integers).
        column: Optional (N,) column indices within each ring (needs ``ring``).
        times: Optional (N,) absolute point times (s); grid cells without a point get the
            earliest time.
        min_range: Points closer than this (m) are misses (e.g. 1.0 for nuScenes).
        sensor: Metadata stored in ``Log.sensor``.
        pose: (4, 4) sensor-to-world pose. When None the points are taken as world coordinates: the
            identity, or, for a georeferenced cloud (most points beyond
            :data:`~mi_lidar.core.frames.NEAR_M`, :func:`georeferenced`), a translation to the rounded centre of its
            bounding box, the points kept relative to it (float32 ranges then keep 0.1 mm, not
            0.25 m) and the centre recorded as ``sensor["cloud_origin"]``.
        origins: Optional (N, 3) ray origins (m, sensor frame) of the points; the sensor's origin when None.

    Returns:
        A log with ``S = 1``.

    Raises:
        LogFormatError: No points, a coordinate beyond :data:`MAX_COORDINATE_M`, or ring/column fields that
            are not non-negative integers, collide, or describe a grid far larger than the cloud.
    """
    stored = np.asarray(points)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    count = len(points)
    source = (sensor or {}).get("source", "point cloud")
    if count == 0:
        raise LogFormatError(f"{source}: the point cloud is empty; a log needs at least one point")
    check_coordinates(points, source)
    if stored.dtype == np.float32 and needs_float64(points):
        message = float32_message(points, source, "float32 coordinates", COARSE_FIX)
        warnings.warn(message, CoarseCoordinatesWarning, stacklevel=2)
    for name, values in (("ring", ring), ("column", column)):
        if values is not None and count:
            _check_index_field(np.asarray(values), name, source, count + MAX_EMPTY_CELLS)
    row, col, height, width = _grid_indices(count, ring, column if ring is not None else None)
    if height * width > count + MAX_EMPTY_CELLS:
        raise LogFormatError(
            f"{source}: ring/column fields describe a {height} x {width} grid for only {count} points; corrupt fields?"
        )
    if ring is not None and len(np.unique(row * width + col)) != count:
        raise LogFormatError(f"{source}: two points share a (ring, column) cell; ring/column fields are inconsistent")
    origins = np.zeros_like(points) if origins is None else np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    if pose is None:  # a cloud in world coordinates: far from the origin, the sensor sits at a local origin
        placed = points[np.isfinite(points).all(axis=1) & np.any(points != origins, axis=1)]
        origin = local_origin(placed) if georeferenced(placed) else np.zeros(3)
        if np.any(origin):
            points = points - origin
            origins = origins - origin if np.any(origins) else origins  # zero: rays from the local origin
            pose = np.eye(4)
            pose[:3, 3] = origin
            sensor = {**(sensor or {}), CLOUD_ORIGIN: origin.tolist()}
    rays = points - origins
    distance = np.linalg.norm(rays, axis=1)
    finite = np.isfinite(distance)
    point_hit = finite & (distance >= min_range) & (distance > 0)
    point_dir = np.where(point_hit[:, None], rays / np.where(point_hit, distance, 1.0)[:, None], 0.0)

    valid = np.zeros((height, width), dtype=bool)
    hit = np.zeros((height, width), dtype=bool)
    ranges = np.full((height, width), np.nan)
    directions = np.zeros((height, width, 3))
    cell_origins = np.zeros((height, width, 3))
    cell_origins[row, col] = origins
    valid[row, col] = True
    hit[row, col] = point_hit
    ranges[row, col] = np.where(point_hit, distance, np.nan)
    directions[row, col] = point_dir
    if ring is not None and height > 1:
        elevation = np.where(hit, np.arcsin(np.clip(directions[..., 2], -1, 1)), np.nan)
        known = hit.any(axis=1)
        medians = np.nanmedian(np.where(known[:, None], elevation, 0.0), axis=1)[known]
        # (equal medians, a planar scanner's rings: no order to follow, and corrcoef would divide by zero)
        flip = len(medians) > 1 and np.ptp(medians) > 0 and np.corrcoef(np.flatnonzero(known), medians)[0, 1] > 0
    else:
        flip = False
    estimate = estimated_directions(directions, hit)
    directions = np.where(hit[..., None], directions, estimate)
    cell_times = np.zeros((height, width))
    if times is not None and count:
        times = np.asarray(times, dtype=np.float64)
        cell_times[:] = np.nanmin(times)
        cell_times[row, col] = times
    grid_attributes = {}
    for name, values in (attributes or {}).items():
        values = np.asarray(values)
        grid = np.zeros((height, width), dtype=values.dtype)
        grid[row, col] = values
        grid_attributes[name] = grid
    if ring is not None:
        ring_grid = np.broadcast_to(np.arange(height, dtype=np.uint16)[:, None], (height, width))
        grid_attributes["ring"] = ring_grid.copy()
    grid_attributes["valid"] = valid & grid_attributes["valid"].astype(bool) if "valid" in grid_attributes else valid
    if flip:
        ranges, hit, directions, cell_times = ranges[::-1], hit[::-1], directions[::-1], cell_times[::-1]
        cell_origins = cell_origins[::-1]
        grid_attributes = {k: v[::-1] for k, v in grid_attributes.items()}
    return Log(
        poses=(np.eye(4) if pose is None else np.asarray(pose))[None],
        directions=directions[None],
        origins=cell_origins[None],
        ranges=ranges[None],
        hit=hit[None],
        times=cell_times[None],
        attributes={k: np.ascontiguousarray(v)[None] for k, v in grid_attributes.items()},
        sensor={"layout": "ring grid" if ring is not None else "points (H=1, W=N)", **(sensor or {})},
    )


def cloud_from_log(log: Log, scan: int = 0, organized: bool = False) -> dict[str, np.ndarray]:
    """The standard point fields of one scan (see the module docstring).

    Args:
        log: Any log.
        scan: Scan index.
        organized: When True return all ``H * W`` rays row-major, misses as NaN ``x y z``;
            otherwise only the hits.

    Returns:
        Field name -> (N,) array, in :data:`STANDARD_FIELDS` order.
    """
    one = log.scan(scan)
    _, height, width = one.shape
    world = CLOUD_ORIGIN in one.sensor  # a world cloud read at a local origin goes back to the world, in float64
    points = one.points_world()[0] if world else one.points_sensor()[0]
    coordinate = np.float64 if world else np.float32
    keep = np.ones((height, width), dtype=bool) if organized else one.hit[0]
    source = next((n for n in INTENSITY_SOURCES if n in one.attributes), None)
    intensity = one.attributes[source][0] if source else np.zeros((height, width))
    rows, cols = np.indices((height, width))
    times = one.times[0]
    return {
        "x": points[..., 0][keep].astype(coordinate),
        "y": points[..., 1][keep].astype(coordinate),
        "z": points[..., 2][keep].astype(coordinate),
        "intensity": np.asarray(intensity, dtype=np.float32)[keep],
        "ring": (height - 1 - rows)[keep].astype(np.uint16),
        "column": cols[keep].astype(np.uint32),
        "time": (times - times.min())[keep].astype(np.float32),
    }


def log_from_fields(
    fields: dict[str, np.ndarray], min_range: float = 0.0, sensor: dict | None = None, start_time: float = 0.0
) -> Log:
    """A one-scan log from named point fields (``x y z`` plus optional standard fields).

    ``ring`` and ``column`` fields select the grid layout; a ``time``/``t``/``timestamp`` field
    (s, relative to ``start_time``) becomes the ray times; :data:`ORIGIN_FIELDS` become the ray
    origins; ``intensity`` and any other numeric field become attributes.
    """
    points = np.stack([np.asarray(fields[c]) for c in ("x", "y", "z")], axis=1)  # stored dtype: float32 is checked
    ring = fields.get("ring")
    column = fields.get("column") if ring is not None else None
    time_name = next((n for n in ("time", "t", "timestamp") if n in fields), None)
    if time_name is None:
        times = np.full(len(points), start_time)
    else:
        times = start_time + np.asarray(fields[time_name], dtype=np.float64)
    origins = np.stack([fields[c] for c in ORIGIN_FIELDS], axis=1) if set(ORIGIN_FIELDS) <= set(fields) else None
    skip = {"x", "y", "z", "ring", "column", time_name, *ORIGIN_FIELDS}
    attributes = {k: np.asarray(v) for k, v in fields.items() if k not in skip and np.asarray(v).dtype.kind in "biuf"}
    return log_from_points(
        points, attributes, ring=ring, column=column, times=times, min_range=min_range, sensor=sensor, origins=origins
    )


def stack_scans(logs: list[Log]) -> Log:
    """Stack one-scan logs into one log, padding smaller grids with invalid miss cells.

    Padded cells have ``hit`` False, ``valid`` False and direction (1, 0, 0); attributes missing
    from some scans are dropped, except ``valid``.
    """
    height = max(log.shape[1] for log in logs)
    width = max(log.shape[2] for log in logs)
    names = set.intersection(*(set(log.attributes) for log in logs)) | {"valid"}

    def pad(array: np.ndarray, fill) -> np.ndarray:
        out = np.full((1, height, width) + array.shape[3:], fill, dtype=array.dtype)
        out[:, : array.shape[1], : array.shape[2]] = array
        return out

    pieces = {k: [] for k in ("directions", "origins", "ranges", "hit", "times")}
    attributes = {n: [] for n in names}
    for log in logs:
        pieces["directions"].append(pad(log.directions, 0.0))
        pieces["origins"].append(pad(log.origins, 0.0))
        pieces["ranges"].append(pad(log.ranges, np.nan))
        pieces["hit"].append(pad(log.hit, False))
        pieces["times"].append(pad(log.times, log.times.min()))
        for n in names:
            attributes[n].append(pad(log.attributes.get(n, np.ones(log.shape, bool)), 0))
    directions = np.concatenate(pieces["directions"])
    empty = np.linalg.norm(directions, axis=-1) == 0
    directions[empty] = (1.0, 0.0, 0.0)
    return Log(
        poses=np.concatenate([log.poses for log in logs]),
        directions=directions,
        origins=np.concatenate(pieces["origins"]),
        ranges=np.concatenate(pieces["ranges"]),
        hit=np.concatenate(pieces["hit"]),
        times=np.concatenate(pieces["times"]),
        attributes={n: np.concatenate(v) for n, v in attributes.items()},
        sensor={**logs[0].sensor, "scans": len(logs)},
    )
