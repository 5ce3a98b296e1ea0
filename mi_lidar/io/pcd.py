"""PCL ``.pcd`` point clouds: ASCII, binary and binary_compressed (LZF) reading; ASCII/binary writing.

Header fields ``FIELDS SIZE TYPE COUNT WIDTH HEIGHT POINTS DATA`` are honoured; fields with
``COUNT > 1`` are read as ``name_0, name_1, ...`` and PCL's ``_`` padding fields are skipped. Logs
are written **organized** (``HEIGHT = H``, ``WIDTH = W``, misses as NaN points) with the standard
fields of :mod:`mi_lidar.io.cloud`, so the ray grid survives a round trip.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.core.log import Log
from mi_lidar.io.cloud import cloud_from_log, log_from_fields

_TYPES = {
    ("F", 4): "f4",
    ("F", 8): "f8",
    ("I", 1): "i1",
    ("I", 2): "i2",
    ("I", 4): "i4",
    ("I", 8): "i8",
    ("U", 1): "u1",
    ("U", 2): "u2",
    ("U", 4): "u4",
    ("U", 8): "u8",
}
_MAX_HEADER_LINES = 64
_MAX_COLUMNS = 1024
START_TIME_COMMENT = "mi_lidar_start_time"


def _lzf_decompress(data: bytes, size: int, path: Path) -> bytes:
    """Decompress an LZF block (liblzf format) to exactly ``size`` bytes."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        control = data[i]
        i += 1
        if control < 32:
            length = control + 1
            if i + length > n:
                raise LogFormatError(f"{path}: LZF literal run overruns the compressed block at byte {i}")
            out += data[i : i + length]
            i += length
        else:
            length = control >> 5
            if length == 7:
                if i >= n:
                    raise LogFormatError(f"{path}: LZF back-reference truncated at byte {i}")
                length += data[i]
                i += 1
            if i >= n:
                raise LogFormatError(f"{path}: LZF back-reference truncated at byte {i}")
            start = len(out) - ((control & 0x1F) << 8) - data[i] - 1
            i += 1
            if start < 0:
                raise LogFormatError(f"{path}: LZF back-reference before the start of the output")
            for k in range(length + 2):
                out.append(out[start + k])
        if len(out) > size:
            break
    if len(out) != size:
        raise LogFormatError(f"{path}: LZF block decompresses to {len(out)} bytes; header says {size}")
    return bytes(out)


_TOO_MANY = "the header's WIDTH/HEIGHT/POINTS are too small or data was appended; correct the header or export again"


def _check_end(path: Path, body: bytes, used: int, what: str) -> None:
    """Refuse a data section with more than whitespace after the ``used`` bytes the header accounts for."""
    if len(body) > used and body[used : used + 64].strip():
        raise LogFormatError(
            f"{path}: {len(body) - used} bytes follow the data the header declares ({what}): {_TOO_MANY}"
        )


def _parse_header(raw: bytes, path: Path) -> tuple[dict, int]:
    """The header keywords and the byte offset of the data section."""
    header, offset = {}, 0
    for _ in range(_MAX_HEADER_LINES):
        end = raw.find(b"\n", offset)
        if end < 0:
            raise LogFormatError(f"{path}: header ends at byte {len(raw)} without a DATA line (truncated?)")
        line = raw[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if line.startswith(f"# {START_TIME_COMMENT} "):
            header[START_TIME_COMMENT] = line.split()[2:3]
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, offset
    raise LogFormatError(f"{path}: no DATA line within the first {_MAX_HEADER_LINES} header lines; not a PCD file?")


def read_pcd(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], int, int]:
    """Read a PCD file.

    Args:
        path: A ``.pcd`` file (ascii, binary or binary_compressed).

    Returns:
        ``(fields, width, height)``: name -> (N,) arrays with ``N = width * height`` (row-major),
        plus the scalar ``mi_lidar_start_time`` when the header carries that comment.

    Raises:
        LogFormatError: Missing/truncated file, inconsistent header (named keyword), unknown
            TYPE/SIZE, or a data section shorter or longer than the header promises.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such PCD file")
    try:
        raw = path.read_bytes()
    except PermissionError as exc:
        raise unreadable(path) from exc
    header, offset = _parse_header(raw, path)
    try:
        names = header["FIELDS"]
        sizes = [int(v) for v in header["SIZE"]]
        types = [v.upper() for v in header["TYPE"]]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(names))]
        width, height = int(header["WIDTH"][0]), int(header.get("HEIGHT", ["1"])[0])
        points = int(header.get("POINTS", [str(width * height)])[0])
        mode = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as exc:
        raise LogFormatError(f"{path}: malformed PCD header ({type(exc).__name__}: {exc})") from exc
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise LogFormatError(f"{path}: FIELDS, SIZE, TYPE and COUNT have different lengths")
    if width < 0 or height < 0 or points != width * height or min(counts, default=1) < 1:
        raise LogFormatError(f"{path}: POINTS {points} != WIDTH {width} x HEIGHT {height} (or a COUNT < 1)")
    if sum(counts) > _MAX_COLUMNS:
        raise LogFormatError(f"{path}: COUNT totals {sum(counts)} values per point; at most {_MAX_COLUMNS} supported")
    if any((t, s) not in _TYPES for t, s in zip(types, sizes)):
        raise LogFormatError(f"{path}: unsupported TYPE/SIZE pair in {list(zip(types, sizes))}")
    columns = [
        (n if c == 1 else f"{n}_{k}", _TYPES[(t, s)])
        for n, s, t, c in zip(names, sizes, types, counts)
        for k in range(c)
    ]
    unique = [(f"{n}__{i}" if n == "_" else n, t) for i, (n, t) in enumerate(columns)]
    if len({n for n, _ in unique}) != len(unique):
        raise LogFormatError(f"{path}: duplicate field names in FIELDS {names}")
    record = np.dtype([(n, "<" + t) for n, t in unique])
    body = raw[offset:]
    if mode == "ascii":
        rows = body.decode("ascii", errors="replace").split()
        if len(rows) != points * len(unique):
            raise LogFormatError(
                f"{path}: ascii data holds {len(rows)} values; the header promises {points * len(unique)} (POINTS "
                f"{points} x {len(unique)} fields): {'truncated?' if len(rows) < points * len(unique) else _TOO_MANY}"
            )
        try:
            table = np.array(rows[: points * len(unique)], dtype=np.float64).reshape(points, len(unique))
        except ValueError as exc:
            raise LogFormatError(f"{path}: non-numeric ascii value ({exc})") from exc
        fields = {n: table[:, i].astype(t) for i, (n, t) in enumerate(unique)}
    elif mode == "binary":
        if len(body) < points * record.itemsize:
            raise LogFormatError(
                f"{path}: binary data is {len(body)} bytes from byte {offset}; expected {points * record.itemsize}"
            )
        _check_end(path, body, points * record.itemsize, f"POINTS {points} x {record.itemsize}-byte records")
        data = np.frombuffer(body, dtype=record, count=points)
        fields = {n: data[n].astype(record[n].newbyteorder("=")) for n in record.names}
    elif mode == "binary_compressed":
        if len(body) < 8:
            raise LogFormatError(f"{path}: binary_compressed block header truncated at byte {offset}")
        compressed, size = np.frombuffer(body[:8], dtype="<u4")
        if size != points * record.itemsize or len(body) < 8 + compressed:
            raise LogFormatError(
                f"{path}: compressed block claims {compressed} -> {size} bytes; expected {points * record.itemsize} "
                f"uncompressed and at most {len(body) - 8} compressed"
            )
        _check_end(path, body, 8 + int(compressed), f"a compressed block of {compressed} bytes")
        data = _lzf_decompress(body[8 : 8 + int(compressed)], int(size), path)
        fields, start = {}, 0
        for name in record.names:
            dtype = record[name]
            fields[name] = np.frombuffer(data, dtype=dtype, count=points, offset=start).astype(dtype.newbyteorder("="))
            start += dtype.itemsize * points
    else:
        raise LogFormatError(f"{path}: DATA {mode!r}; expected ascii, binary or binary_compressed")
    fields = {n: v for n, v in fields.items() if not n.startswith("_")}
    if header.get(START_TIME_COMMENT):
        try:
            fields[START_TIME_COMMENT] = np.float64(header[START_TIME_COMMENT][0])
        except ValueError as exc:
            raise LogFormatError(f"{path}: malformed {START_TIME_COMMENT} comment ({exc})") from exc
    return fields, width, height


def write_pcd(
    path: str | os.PathLike,
    fields: dict[str, np.ndarray],
    width: int | None = None,
    height: int = 1,
    binary: bool = True,
    start_time: float | None = None,
) -> Path:
    """Write named (N,) fields as a PCD v0.7 file, atomically.

    Args:
        path: Destination ``.pcd``.
        fields: Name -> (N,) numeric array (dtype kept: int/uint 8-64 bit, float32/64).
        width, height: Organized size (``width * height == N``); unorganized ``N x 1`` by default.
        binary: ``DATA binary`` when True, ``DATA ascii`` otherwise.
        start_time: Optional absolute time (s) of the cloud's ``time`` field origin, stored as the
            header comment ``# mi_lidar_start_time <t>``.
    """
    arrays = {n: np.asarray(v) for n, v in fields.items()}
    count = len(next(iter(arrays.values())))
    width = count if width is None else width
    if any(a.shape != (count,) for a in arrays.values()) or width * height != count:
        raise ValueError(f"write_pcd: every field must be ({count},) and width x height == {count}")
    kinds = {"f": "F", "i": "I", "u": "U", "b": "U"}
    types = [kinds[a.dtype.kind] for a in arrays.values()]
    sizes = [a.dtype.itemsize for a in arrays.values()]
    header = (
        "\n".join(
            [
                "# .PCD v0.7 - Point Cloud Data file format (written by mi-lidar)",
                *([] if start_time is None else [f"# {START_TIME_COMMENT} {start_time!r}"]),
                "VERSION 0.7",
                "FIELDS " + " ".join(arrays),
                "SIZE " + " ".join(map(str, sizes)),
                "TYPE " + " ".join(types),
                "COUNT " + " ".join("1" for _ in arrays),
                f"WIDTH {width}",
                f"HEIGHT {height}",
                "VIEWPOINT 0 0 0 1 0 0 0",
                f"POINTS {count}",
                f"DATA {'binary' if binary else 'ascii'}",
            ]
        )
        + "\n"
    )
    record = np.dtype([(n, "<" + a.dtype.str[1:]) for n, a in arrays.items()])
    table = np.empty(count, dtype=record)
    for name, values in arrays.items():
        table[name] = values
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as stream:
            stream.write(header.encode("ascii"))
            if binary:
                stream.write(table.tobytes())
            else:
                formats = {4: "%.9g", 8: "%.17g"}
                columns = [
                    np.char.mod(formats[a.dtype.itemsize] if a.dtype.kind == "f" else "%d", a) for a in arrays.values()
                ]
                stream.write("\n".join(" ".join(row) for row in zip(*columns)).encode("ascii") + b"\n")
    return Path(path)


def write_pcd_log(log: Log, path: str | os.PathLike, scan: int = 0, binary: bool = True) -> Path:
    """Write one scan as an organized ``H x W`` PCD (misses are NaN points)."""
    _, height, width = log.shape
    return write_pcd(
        path,
        cloud_from_log(log, scan, organized=True),
        width=width,
        height=height,
        binary=binary,
        start_time=float(log.times[scan].min()),
    )


def read_pcd_log(path: str | os.PathLike, min_range: float = 0.0) -> Log:
    """Read a PCD as a one-scan log (ring grid from a ``ring`` field, else from an organized
    ``HEIGHT > 1`` layout, else ``H = 1``)."""
    fields, width, height = read_pcd(path)
    start = float(fields.pop(START_TIME_COMMENT, 0.0))
    missing = [c for c in ("x", "y", "z") if c not in fields]
    if missing:
        raise LogFormatError(f"{path}: PCD lacks fields {missing}; expected x y z")
    if "ring" not in fields and height > 1:
        rows, cols = np.indices((height, width))
        fields = {**fields, "ring": (height - 1 - rows).ravel(), "column": cols.ravel()}
    return log_from_fields(fields, min_range=min_range, sensor={"name": "pcd", "source": str(path)}, start_time=start)
