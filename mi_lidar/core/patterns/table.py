"""User firing tables: a pattern read from, or written to, a CSV or NPY table of angles and times."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path, atomic_write
from mi_lidar.core.errors import NUMPY_FILE_ERRORS, PatternError, numpy_file_problem, unreadable
from mi_lidar.core.patterns.firing import FiringPattern, positive_float

_CSV_ANGLES = ("elevation_deg", "azimuth_deg")
_CSV_GRID = ("row", "col")
_DEFAULT_PERIOD = 0.1


def from_table(path: str | os.PathLike, period: float | None = None) -> FiringPattern:
    """Read a user's firing pattern from a CSV or NPY table.

    Formats (angles in degrees, elevation positive up, azimuth counter-clockwise from +x):

    - **CSV** with a header row naming the columns, in any order: ``elevation_deg``,
      ``azimuth_deg`` (required), ``time_s`` (optional, seconds since the sweep start),
      ``row`` and ``col`` (optional, together: 0-based grid position; every cell of the
      ``(max row + 1) x (max col + 1)`` grid must appear exactly once). Without ``row``/``col``
      the rays form one row in file order.
    - **NPY** array of shape ``(N, 2|3)`` (one row of N rays) or ``(H, W, 2|3)`` (a grid);
      the last axis is ``elevation_deg, azimuth_deg[, time_s]``.

    Without times, rays fire evenly spaced in row-major order over ``period``. With times
    and ``period=None``, the period is the last time plus the mean spacing of the times
    (0.1 s if all rays fire at once).

    Args:
        path: ``.csv`` or ``.npy`` file.
        period: Sweep duration, s; None infers it as above (0.1 s without times).

    Returns:
        The pattern, named after the file stem.

    Raises:
        PatternError: The file is missing or malformed, a column is missing or not numeric,
            a grid cell is missing or repeated, an angle is not finite, or a time lies
            outside [0, period).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".csv":
        columns = _read_csv_columns(p)
    elif suffix == ".npy":
        columns = _read_npy_columns(p)
    else:
        raise PatternError(f"from_table: unsupported table {os.fspath(path)!r}; give a .csv or .npy file")
    where = f"table {os.fspath(path)}"
    for key in _CSV_ANGLES:
        bad = np.flatnonzero(~np.isfinite(columns[key]))
        if bad.size:
            raise PatternError(
                f"{where}: {key} of ray {bad[0]} is {columns[key][bad[0]]!r}; every angle must be "
                "a finite number of degrees"
            )
    steep = np.flatnonzero(np.abs(columns["elevation_deg"]) > 90.0)
    if steep.size:
        raise PatternError(
            f"{where}: elevation_deg of ray {steep[0]} is {columns['elevation_deg'][steep[0]]!r}; "
            "elevations lie in [-90, 90] degrees"
        )
    shape, cell = _grid_cells(where, columns)
    n = columns["elevation_deg"].size
    times = columns.get("time_s")
    if period is not None:
        period = positive_float(where, "period", period)
    if times is None:
        period = _DEFAULT_PERIOD if period is None else period
        times = np.arange(n) * (period / n)
    elif period is None:
        spacing = (times.max() - times.min()) / max(n - 1, 1)
        period = times.max() + spacing if spacing > 0 else _DEFAULT_PERIOD

    def grid(values: np.ndarray) -> np.ndarray:
        out = np.empty(shape[0] * shape[1])
        out[cell] = values
        return out.reshape(shape)

    try:
        return FiringPattern(
            name=p.stem,
            elevation=grid(np.radians(columns["elevation_deg"])),
            azimuth=grid(np.radians(columns["azimuth_deg"])),
            time=grid(times),
            period=period,
        )
    except PatternError as exc:  # name the file, not only the pattern's name (its stem)
        raise PatternError(f"{where}: {exc}") from None


def to_table(pattern: FiringPattern, path: str | os.PathLike) -> Path:
    """Write a pattern as a table that :func:`from_table` reads back.

    CSV gets the columns ``elevation_deg, azimuth_deg, time_s, row, col`` (17 significant
    digits, so angles survive the round trip); NPY gets an ``(H, W, 3)`` float64 array of
    ``elevation_deg, azimuth_deg, time_s``. Neither stores the period, the beam origins or
    the beam ids: pass ``period=`` to :func:`from_table` to restore the period exactly.

    Args:
        pattern: The pattern to write.
        path: Destination ending in ``.csv`` or ``.npy``.

    Returns:
        The path written.

    Raises:
        PatternError: The suffix is neither ``.csv`` nor ``.npy``.
    """
    p = Path(path)
    stack = np.stack([np.degrees(pattern.elevation), np.degrees(pattern.azimuth), pattern.time], axis=-1)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        atomic_write(p, lambda stream: np.save(stream, stack))
    elif suffix == ".csv":
        h, w = pattern.shape
        rows, cols = np.divmod(np.arange(h * w), w)
        with atomic_path(p) as tmp, tmp.open("w", newline="") as f:
            out = csv.writer(f)
            out.writerow([*_CSV_ANGLES, "time_s", *_CSV_GRID])
            for (el, az, t), r, c in zip(stack.reshape(-1, 3), rows, cols):
                out.writerow([f"{el:.17g}", f"{az:.17g}", f"{t:.17g}", r, c])
    else:
        raise PatternError(f"to_table: unsupported table {os.fspath(path)!r}; use .csv or .npy")
    return p


def _read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    """Columns of a pattern CSV as arrays; see :func:`from_table` for the format."""
    where = f"table {os.fspath(path)}"
    try:
        with path.open(newline="") as f:
            reader = csv.reader(f)
            header = [name.strip() for name in next(reader, [])]
            records = [(reader.line_num, [v.strip() for v in row]) for row in reader if row]  # blank lines skipped
    except PermissionError as exc:  # (its fix was to check the path: the path was right)
        raise unreadable(path, "pattern table", PatternError) from exc
    except OSError as exc:
        raise PatternError(f"cannot read {where} ({exc.strerror}); check the path") from exc
    except (UnicodeDecodeError, csv.Error) as exc:
        raise PatternError(f"{where} is not a text CSV file ({exc})") from exc
    missing = [key for key in _CSV_ANGLES if key not in header]
    if missing:
        raise PatternError(
            f"{where}: missing column(s) {', '.join(missing)} in header {header!r}; the header "
            "must read elevation_deg,azimuth_deg[,time_s][,row,col]"
        )
    if ("row" in header) != ("col" in header):
        raise PatternError(f"{where}: header {header!r} has only one of row/col; give both or none")
    if not records:
        raise PatternError(f"{where} holds a header but no rays; add one line per ray")
    longer = next(((line, len(rec)) for line, rec in records if len(rec) > len(header)), None)
    if longer is not None:
        raise PatternError(
            f"{where}, line {longer[0]}: {longer[1]} fields under a header of {len(header)}; one value per column"
        )
    wanted = [key for key in (*_CSV_ANGLES, "time_s", *_CSV_GRID) if key in header]
    columns = {}
    for key in wanted:
        j = header.index(key)
        values = np.empty(len(records))
        for i, (line, rec) in enumerate(records):
            try:
                values[i] = float(rec[j])
            except (ValueError, IndexError):
                text = rec[j] if j < len(rec) else ""
                raise PatternError(
                    f"{where}, line {line}: {key} is {text!r}, not a number; fill every column"
                ) from None
        columns[key] = values
    return columns


def _read_npy_columns(path: Path) -> dict[str, np.ndarray]:
    """Columns of a pattern NPY as flat arrays in row-major grid order, with the grid shape."""
    where = f"table {os.fspath(path)}"
    if not path.is_file():
        raise PatternError(f"cannot read {where} (no such file); check the path")
    try:
        array = np.load(path, allow_pickle=False)
    except PermissionError as exc:  # (it was 'not a plain numeric NPY array (PermissionError ...)')
        raise unreadable(path, "pattern table", PatternError) from exc
    except NUMPY_FILE_ERRORS as exc:
        raise PatternError(f"{where} is not a plain numeric NPY array ({numpy_file_problem(exc)})") from None
    if array.ndim not in (2, 3) or array.shape[-1] not in (2, 3) or 0 in array.shape:
        raise PatternError(
            f"{where}: array of shape {array.shape}; expected (N, 2|3) or (H, W, 2|3) with "
            "elevation_deg, azimuth_deg[, time_s] on the last axis"
        )
    if not np.issubdtype(array.dtype, np.number):
        raise PatternError(f"{where}: dtype {array.dtype} is not numeric; save float degrees")
    flat = array.reshape(-1, array.shape[-1]).astype(np.float64)
    columns = {"elevation_deg": flat[:, 0], "azimuth_deg": flat[:, 1]}
    if array.shape[-1] == 3:
        columns["time_s"] = flat[:, 2]
    if array.ndim == 3:
        rows, cols = np.divmod(np.arange(flat.shape[0]), array.shape[1])
        columns["row"], columns["col"] = rows.astype(np.float64), cols.astype(np.float64)
    return columns


def _grid_cells(where: str, columns: dict[str, np.ndarray]) -> tuple[tuple[int, int], np.ndarray]:
    """Grid shape and the flat row-major cell of every ray of a table.

    Args:
        where: Context for error messages.
        columns: Table columns; ``row`` and ``col`` optional.

    Returns:
        ``((H, W), cell)`` with ``cell`` an (N,) int array, a permutation of ``arange(H * W)``.

    Raises:
        PatternError: Negative or fractional indices, or a cell missing or repeated.
    """
    n = columns["elevation_deg"].size
    if "row" not in columns:
        return (1, n), np.arange(n)
    index = np.stack([columns["row"], columns["col"]])
    if not np.all(np.isfinite(index)) or np.any(index < 0) or np.any(index != np.round(index)):
        bad = np.flatnonzero(~(np.isfinite(index) & (index >= 0) & (index == np.round(index))))
        ray = int(bad[0] % n)
        raise PatternError(
            f"{where}: ray {ray} has row, col = {index[0, ray]!r}, {index[1, ray]!r}; grid "
            "indices must be integers >= 0"
        )
    if index.max() >= n:  # every cell appears once, so H * W == n and no index reaches n
        ray = int(np.argmax(index.max(axis=0)))
        raise PatternError(
            f"{where}: ray {ray} has row, col = {index[0, ray]!r}, {index[1, ray]!r}, beyond a grid of "
            f"{n} rays; list every cell of the grid exactly once"
        )
    rows, cols = index.astype(np.int64)
    shape = (int(rows.max()) + 1, int(cols.max()) + 1)
    cell = rows * shape[1] + cols
    counts = np.bincount(cell, minlength=shape[0] * shape[1])
    if np.any(counts != 1):
        first = int(np.flatnonzero(counts != 1)[0])
        what = "missing" if counts[first] == 0 else f"given {counts[first]} times"
        raise PatternError(
            f"{where}: grid cell row={first // shape[1]}, col={first % shape[1]} of the "
            f"{shape[0]} x {shape[1]} grid is {what}; list every cell exactly once"
        )
    return shape, cell
