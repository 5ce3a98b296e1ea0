"""PLY point clouds (binary little-endian or ASCII) via ``plyfile``.

One ``vertex`` element holds float32 ``x y z`` (float64 for georeferenced points) plus one
property per attribute. PLY knows the types int8/16/32, uint8/16/32, float32 and float64, so those
attribute dtypes round-trip exactly;
bool attributes are stored as uint8 and int64/uint64 ones as int32/uint32 when every value fits
(they read back with the narrower dtype); anything else is rejected with a clear message.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import plyfile

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.core.frames import needs_float64
from mi_lidar.core.log import Log
from mi_lidar.io.cloud import cloud_from_log, log_from_fields

_PLY_KINDS = {np.dtype(t) for t in ("i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8")}
_COORDS = ("x", "y", "z")
START_TIME_COMMENT = "mi_lidar_start_time"


def _ply_dtype(name: str, values: np.ndarray) -> np.dtype:
    """The PLY-storable dtype for attribute ``name`` (see the module docstring)."""
    dtype = values.dtype
    if dtype.newbyteorder("=") in _PLY_KINDS:
        return dtype.newbyteorder("=")
    if dtype == np.bool_:
        return np.dtype("u1")
    for wide, narrow in (("i8", "i4"), ("u8", "u4")):
        if dtype == np.dtype(wide):
            info = np.iinfo(narrow)
            if values.size == 0 or (values.min() >= info.min and values.max() <= info.max):
                return np.dtype(narrow)
            raise ValueError(f"PLY attribute {name!r}: {dtype} values exceed the {narrow} range PLY supports")
    raise ValueError(f"PLY attribute {name!r} has dtype {dtype}; PLY stores only int/uint 8-32 bit and float32/64")


def write_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    attributes: dict[str, np.ndarray] | None = None,
    binary: bool = True,
    comments: list[str] | None = None,
) -> Path:
    """Write points and per-point attributes as a PLY ``vertex`` element, atomically.

    Args:
        path: Destination ``.ply`` file.
        points: (N, 3) coordinates (m), stored as float32 ``x y z``, or float64 when they are float64
            and float32 would keep them more coarsely than 1 mm (georeferenced points).
        attributes: Name -> (N,) array per point (e.g. ``intensity``, ``ring``); dtypes kept.
        binary: Binary little-endian when True, ASCII otherwise.
        comments: Optional header comment lines.

    Returns:
        The destination path.

    Raises:
        ValueError: Wrong shapes, a name clash with ``x y z``, or a dtype PLY cannot store.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"write_ply: points have shape {points.shape}; expected (N, 3)")
    attributes = dict(attributes or {})
    far = points.dtype == np.float64 and needs_float64(points)
    fields = [(c, "f8" if far else "f4") for c in _COORDS]
    for name, values in attributes.items():
        values = np.asarray(values)
        if name in _COORDS:
            raise ValueError(f"write_ply: attribute name {name!r} clashes with a coordinate")
        if values.shape != (len(points),):
            raise ValueError(f"write_ply: attribute {name!r} has shape {values.shape}; expected ({len(points)},)")
        fields.append((name, _ply_dtype(name, values).str))
    vertex = np.empty(len(points), dtype=fields)
    for i, c in enumerate(_COORDS):
        vertex[c] = points[:, i]
    for name, values in attributes.items():
        vertex[name] = values
    element = plyfile.PlyElement.describe(vertex, "vertex")
    with atomic_path(path) as tmp:
        plyfile.PlyData([element], text=not binary, byte_order="<", comments=comments or []).write(str(tmp))
    return Path(path)


def _load(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], list[str]]:
    """Points, attributes and header comments of a PLY file (see :func:`read_ply`)."""
    try:
        with open(path, "rb") as stream:
            text = b"format ascii" in stream.read(64)  # (plyfile wraps an ASCII stream in a reader left open)
            stream.seek(0)
            data = plyfile.PlyData.read(str(path) if text else stream)
            vertex = data["vertex"].data
            if not text:
                _check_binary_end(path, stream, data)
        if text:
            _check_text_end(path, data)
    except (FileNotFoundError, IsADirectoryError) as exc:
        raise LogFormatError(f"{path}: no such PLY file") from exc
    except PermissionError as exc:
        raise unreadable(path) from exc
    except KeyError as exc:
        raise LogFormatError(f"{path}: no 'vertex' element; expected a point cloud") from exc
    except LogFormatError:
        raise
    except Exception as exc:  # plyfile raises PlyParseError, ValueError, struct errors, ...
        raise LogFormatError(f"{path}: not a readable PLY file ({type(exc).__name__}: {exc})") from exc
    names = vertex.dtype.names or ()
    missing = [c for c in _COORDS if c not in names]
    if missing:
        raise LogFormatError(f"{path}: vertex element lacks properties {missing}; expected x y z")
    wide = any(vertex[c].dtype.itemsize > 4 for c in _COORDS)  # double coordinates (georeferenced) stay float64
    points = np.stack([vertex[c] for c in _COORDS], axis=1).astype(np.float64 if wide else np.float32, copy=False)
    attributes = {}
    for name in names:
        if name not in _COORDS:  # views into the vertex table, copied only to swap a foreign byte order
            column = vertex[name]
            attributes[name] = column if column.dtype.isnative else column.astype(column.dtype.newbyteorder("="))
    return points, attributes, data.comments


def _element_counts(data: plyfile.PlyData) -> str:
    """The header's element counts as written there ("element vertex 54")."""
    return ", ".join(f"'element {element.name} {element.count}'" for element in data.elements)


def _check_binary_end(path: Path, stream, data: plyfile.PlyData) -> None:
    """Refuse bytes after the elements a binary PLY's header declares (a count too small drops points)."""
    end, size = stream.tell(), os.fstat(stream.fileno()).st_size
    if size > end and stream.read(min(size - end, 64)).strip():
        raise LogFormatError(
            f"{path}: {size - end} bytes follow the data its header declares ({_element_counts(data)}): the count is "
            "too small or data was appended; correct the header or export the file again"
        )


def _check_text_end(path: Path, data: plyfile.PlyData) -> None:
    """Refuse values after the elements an ASCII PLY's header declares (when no element has list properties)."""
    if any(isinstance(p, plyfile.PlyListProperty) for element in data.elements for p in element.properties):
        return
    raw = path.read_bytes()
    body = raw[raw.index(b"\n", raw.index(b"end_header")) + 1 :]
    found = len(body.split())
    declared = sum(element.count * len(element.properties) for element in data.elements)
    if found > declared:
        raise LogFormatError(
            f"{path}: {found} values follow the header, which declares {declared} ({_element_counts(data)}): the "
            "count is too small or data was appended; correct the header or export the file again"
        )


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read the ``vertex`` element of a PLY file.

    Args:
        path: A ``.ply`` file (ASCII or binary).

    Returns:
        ``(points, attributes)``: (N, 3) float32 coordinates and name -> (N,) arrays with the
        stored dtypes (native byte order).

    Raises:
        LogFormatError: Missing, unreadable, truncated or malformed file, data beyond what the header
            declares, or no ``vertex`` element with ``x y z`` properties.
    """
    points, attributes, _ = _load(Path(path))
    return points, attributes


def write_ply_log(log: Log, path: str | os.PathLike, scan: int = 0, binary: bool = True) -> Path:
    """Write the hits of one scan with the standard fields ``x y z intensity ring column time``;
    the header comment ``mi_lidar_start_time <t>`` holds the absolute time (s) of ``time = 0``."""
    cloud = cloud_from_log(log, scan)
    points = np.stack([cloud.pop(c) for c in _COORDS], axis=1)
    start = float(log.times[scan].min())
    return write_ply(path, points, cloud, binary=binary, comments=[f"{START_TIME_COMMENT} {start!r}"])


def read_ply_log(path: str | os.PathLike, min_range: float = 0.0) -> Log:
    """Read a PLY point cloud as a one-scan log (ring grid when ``ring`` is a property, else H = 1)."""
    points, attributes, comments = _load(Path(path))
    fields = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], **attributes}
    start = 0.0
    for comment in comments:
        if comment.startswith(START_TIME_COMMENT + " "):
            try:
                start = float(comment.split()[1])
            except (IndexError, ValueError) as exc:
                raise LogFormatError(f"{path}: malformed {START_TIME_COMMENT} comment {comment!r}") from exc
    return log_from_fields(fields, min_range=min_range, sensor={"name": "ply", "source": str(path)}, start_time=start)
