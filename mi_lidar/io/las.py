"""ASPRS LAS point clouds via ``laspy`` (LAS 1.4, point format 6).

Writing stores the hits of one scan: coordinates at 0.1 mm resolution, ``gps_time`` = the ray's
absolute time (s), the standard ``intensity`` = intensity rounded and clipped to 0..65535 (for
viewers), and extra-byte dimensions ``lidar_intensity`` (float32, exact), ``ring`` (uint16) and
``column`` (uint32) so the ray grid can be rebuilt. Reading uses those extra dimensions when
present (``H = 1, W = N`` otherwise). Compressed ``.laz`` needs a laspy LAZ backend
(``pip install 'laspy[lazrs]'``).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import laspy
import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.core.log import Log
from mi_lidar.io.cloud import cloud_from_log, log_from_fields

COORDINATE_SCALE = 1e-4
VLR_HEADER_BYTES = 54
EVLR_HEADER_BYTES = 60


def _check_record_counts(path: Path, head: bytes, size: int) -> None:
    """Reject VLR / EVLR counts the file cannot hold (laspy would loop over them at end of file).

    Public header fields (LAS 1.0-1.4): ``header_size`` u16 at byte 94, ``number_of_vlrs`` u32 at
    100, and for 1.4 ``start_of_first_evlr`` u64 at 235 and ``number_of_evlrs`` u32 at 243.

    Args:
        path: the file (for messages).
        head: its first 247 bytes (fewer for a shorter file).
        size: its size, bytes.
    """
    if len(head) < 104 or head[:4] != b"LASF":
        return  # laspy reports the bad signature or the short header
    header_size, _, vlrs = struct.unpack_from("<HII", head, 94)
    if header_size > size:
        raise LogFormatError(f"{path}: header field header_size = {header_size} exceeds the {size}-byte file")
    if vlrs * VLR_HEADER_BYTES > size - header_size:
        raise LogFormatError(
            f"{path}: header field number_of_vlrs = {vlrs} needs at least {vlrs * VLR_HEADER_BYTES} bytes after "
            f"the {header_size}-byte header; the file has {size} bytes (corrupt header)"
        )
    if head[25] >= 4 and len(head) == 247 and header_size >= 247:
        start, evlrs = struct.unpack_from("<QI", head, 235)
        if evlrs and (start > size or evlrs * EVLR_HEADER_BYTES > size - start):
            raise LogFormatError(
                f"{path}: header fields start_of_first_evlr = {start} and number_of_evlrs = {evlrs} do not fit "
                f"the {size}-byte file (corrupt header)"
            )


def _check_header_values(path: Path, header, need: int, size: int) -> None:
    """Refuse non-finite or zero coordinate scales, non-finite offsets, and (uncompressed) whole point records
    after the ``point_count`` the header counts, before the extended VLRs or waveform data (a count too small)."""
    scales, offsets = np.asarray(header.scales, dtype=float), np.asarray(header.offsets, dtype=float)
    if not (np.isfinite(scales).all() and np.all(scales != 0) and np.isfinite(offsets).all()):
        raise LogFormatError(
            f"{path}: header fields scale {scales.tolist()} and offset {offsets.tolist()} must be finite, scales "
            "non-zero (corrupt header); export the file again"
        )
    if header.are_points_compressed:
        return
    starts = (header.start_of_first_evlr if header.number_of_evlrs else 0, header.start_of_waveform_data_packet_record)
    end = min([size, *(int(start) for start in starts if start and start >= need)])
    if end - need >= header.point_format.size:
        raise LogFormatError(
            f"{path}: {(end - need) // header.point_format.size} whole point records follow the point_count = "
            f"{header.point_count} the header counts: the count is too small or data was appended; correct the "
            "header or export the file again"
        )


def _check_span(path, scan: int, local: np.ndarray) -> None:
    """Refuse points that lie farther from the file's offset than LAS's 32-bit integers reach at
    :data:`COORDINATE_SCALE` (214,748 m), which laspy reports as a bare ``OverflowError``.

    Args:
        path: The file being written (for the message).
        scan: The scan written.
        local: (N, 3) coordinates minus the file's offsets (m, >= 0).
    """
    reach = np.iinfo(np.int32).max * COORDINATE_SCALE
    if len(local) and local.max() > reach:
        axis = "xyz"[int(np.argmax(local.max(axis=0)))]
        raise LogFormatError(
            f"{path}: the hits of scan {scan} span {local.max():,.0f} m along {axis}; LAS stores coordinates as 32-bit "
            f"integers of {COORDINATE_SCALE} m, at most {reach:,.0f} m apart: write .ply, .pcd or .npz, or drop the "
            "far points (a range that long is a damaged reading)"
        )


def write_las_log(log: Log, path: str | os.PathLike, scan: int = 0) -> Path:
    """Write the hits of one scan as a LAS 1.4 file, atomically (see the module docstring)."""
    cloud = cloud_from_log(log, scan)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams(name="lidar_intensity", type=np.float32),
            laspy.ExtraBytesParams(name="ring", type=np.uint16),
            laspy.ExtraBytesParams(name="column", type=np.uint32),
        ]
    )
    xyz = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    _check_span(path, scan, xyz - header.offsets)
    header.scales = np.full(3, COORDINATE_SCALE)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = np.clip(np.round(cloud["intensity"]), 0, 65535).astype(np.uint16)
    one = log.scan(scan)
    las.gps_time = one.times[0].min() + cloud["time"].astype(np.float64)
    las.lidar_intensity = cloud["intensity"]
    las.ring = cloud["ring"]
    las.column = cloud["column"]
    with atomic_path(path) as tmp:
        las.write(str(tmp))
    return Path(path)


def read_las(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, np.ndarray], float]:
    """Read the points of a LAS/LAZ file and the attributes a log needs.

    Args:
        path: A ``.las`` or ``.laz`` file.

    Returns:
        ``(points, attributes, start)``: (N, 3) float64 coordinates (m); ``intensity`` (float32,
        ``lidar_intensity`` when present), ``ring`` and ``column`` when present, and ``time`` (s
        since ``start``, the earliest ``gps_time``) when the points have a ``gps_time``.

    Raises:
        LogFormatError: Missing, unreadable, truncated or malformed file (a header whose point count, scale or
            offset disagrees with the data), or LAZ without a backend.
    """
    path = Path(path)
    try:
        stream = open(path, "rb")  # closed by the with block below
    except (FileNotFoundError, IsADirectoryError) as exc:
        raise LogFormatError(f"{path}: no such LAS file") from exc
    except PermissionError as exc:
        raise unreadable(path) from exc
    with stream:
        size = os.fstat(stream.fileno()).st_size
        _check_record_counts(path, stream.read(247), size)
        stream.seek(0)
        try:
            with laspy.open(stream, closefd=False) as reader:
                header = reader.header
                need = header.offset_to_point_data + header.point_count * header.point_format.size
                if not header.are_points_compressed and need > size:
                    raise LogFormatError(
                        f"{path}: header field point_count = {header.point_count} needs {need} bytes of "
                        f"{header.point_format.size}-byte records from byte {header.offset_to_point_data}; "
                        f"the file has {size} (truncated or corrupt header)"
                    )
                _check_header_values(path, header, need, size)
                las = reader.read()
            names = set(las.point_format.dimension_names)
            points = _coordinates(las)
            attributes = {
                "intensity": np.asarray(
                    las["lidar_intensity"] if "lidar_intensity" in names else las.intensity, dtype=np.float32
                )
            }
            for name in ("ring", "column"):
                if name in names:
                    attributes[name] = np.asarray(las[name])
            start = 0.0
            if "gps_time" in names and len(las.gps_time):
                gps_time = np.asarray(las.gps_time)
                start = float(gps_time.min())
                attributes["time"] = gps_time - start
        except LogFormatError:
            raise
        except Exception as exc:  # laspy raises LaspyException, ValueError, struct and IO errors.
            hint = " (.laz needs `pip install 'laspy[lazrs]'`)" if path.suffix.lower() == ".laz" else ""
            raise LogFormatError(f"{path}: not a readable LAS file ({type(exc).__name__}: {exc}){hint}") from exc
    return points, attributes, start


def _coordinates(las) -> np.ndarray:
    """(N, 3) float64 coordinates (m) of the points of ``las``: stored integers times scale plus offset,
    as laspy's ``x``, ``y``, ``z``, written straight into one array."""
    raw, header = las.points.array, las.header
    points = np.empty((len(raw), 3))
    for axis, name in enumerate("XYZ"):
        np.multiply(raw[name], header.scales[axis], out=points[:, axis])
        points[:, axis] += header.offsets[axis]
    return points


def read_las_log(path: str | os.PathLike, min_range: float = 0.0) -> Log:
    """Read a LAS/LAZ file as a one-scan log.

    Raises:
        LogFormatError: Missing, truncated or malformed file, or LAZ without a backend.
    """
    points, attributes, start = read_las(path)
    fields = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], **attributes}
    return log_from_fields(fields, min_range=min_range, sensor={"name": "las", "source": str(path)}, start_time=start)
