"""CARMEN planar laser logs (``FLASER`` / ``RLASER`` messages, plain or gzip) -> :class:`~mi_lidar.core.log.Log`.

A message line is ``FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta ipc_timestamp host
logger_timestamp``; ``x y theta`` is the (in corrected logs, SLAM-corrected) laser pose in the
map frame (m, rad). Each message becomes one scan of ``H = n`` beams by ``W = 1`` firing, so that
per-beam quantities (bias, angle offsets) are per row, as for every other sensor:

- beam ``i`` points at ``-pi/2 + i * pi / n`` in the laser frame (``pi / (n - 1)`` when ``n`` is
  odd, e.g. 181 or 361 beams covering 180 deg inclusive), in the horizontal plane;
- the pose is the planar transform (rotation ``theta`` about z, translation ``(x, y, 0)``);
- a reading at or above the sensor's no-return value (less 1.5 cm) is a miss. That value is detected
  from the log (:func:`detect_max_range`: the spike of readings at the top of the range scale: the
  SICK maximum 81.83 m in the Intel log, 50 m in logs that clip there, a band of codes such as
  51.05-51.16 m or 81.83 and 81.91 m in others) or given as ``max_range``;
- beam ``i`` is timed ``ipc_timestamp + i * sweep_s / n`` (SICK LMS 2xx: 180 deg of a 75 Hz
  mirror revolution, ``sweep_s = 1 / 150`` s).

The raw odometry poses are kept in ``sensor['odometry']`` (an (S, 3) list of x, y, theta).
"""

from __future__ import annotations

import gzip
import os
import zlib
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.core.log import Log

SICK_SWEEP_S = 1.0 / 150.0
MISS_MARGIN = 0.015  # m: readings this close to the no-return value are misses (the real-planar protocol)
MIN_SHARE_AT_MAX = 1e-3  # share of all readings a 1 cm bin must hold to be a no-return code
SPIKE_RATIO = 20.0  # a no-return code holds this many times the readings of a 1 cm bin just below it
NO_RETURN_BAND = 0.2  # m: no-return codes of one scanner lie within this band below the largest one
BACKGROUND = 5.0  # m: the readings this far below the codes give the background density of real returns


def text_lines(path: Path) -> list[str]:
    """Decoded text lines of a plain or gzip-compressed file."""
    try:
        raw = path.read_bytes()
    except PermissionError as exc:
        raise unreadable(path, "log") from exc
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError, zlib.error) as exc:
            raise LogFormatError(f"{path}: corrupt or truncated gzip stream ({exc})") from exc
    return raw.decode("utf-8", errors="replace").splitlines()


def parse_message(tokens: list[str], number: int) -> np.ndarray:
    """The (n + 7,) values of one laser line's ``tokens`` (``NAME n ranges... x y theta odom_x odom_y
    odom_theta timestamp host logger_timestamp``): its n ranges, pose, odometry and timestamp.

    Raises:
        LogFormatError: a beam count below 2, a non-numeric value, too few fields, or more than the count
            allows (``n`` smaller than the ranges given) (``number``: the line's number, named in the message).
    """
    name = tokens[0]
    try:
        n = int(tokens[1])
        if n <= 1:
            raise ValueError(f"beam count {n} must be > 1")
        values = np.array(tokens[2 : 2 + n + 7], dtype=np.float64)
    except (IndexError, ValueError) as exc:
        raise LogFormatError(f"line {number}: malformed {name} message ({exc}): repair or delete the line") from exc
    if len(values) != n + 7 or len(tokens) < n + 10:
        raise LogFormatError(
            f"line {number}: {name} with n={n} needs {n + 10} fields (n ranges + 10); found {len(tokens)} "
            "(truncated?): repair or delete the line"
        )
    if len(tokens) > n + 11 or (len(tokens) == n + 11 and not _is_number(tokens[-1])):
        raise LogFormatError(
            f"line {number}: {name} with n={n} has {len(tokens)} fields, where n ranges + 10 (or 11 with the logger "
            f"timestamp) make {n + 10} or {n + 11}: the beam count {n} is smaller than the ranges on the line; repair "
            "the count or delete the line"
        )
    return values


def _is_number(token: str) -> bool:
    """Whether ``token`` reads as a float."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def beam_angles(n: int) -> np.ndarray:
    """(n,) beam angles (rad) in the laser frame for an ``n``-beam 180-degree CARMEN scan."""
    step = np.pi / (n - 1) if n % 2 else np.pi / n
    return -np.pi / 2 + np.arange(n) * step


def detect_max_range(readings: np.ndarray) -> float:
    """The sensor's no-return value in a planar log's readings (m), or ``inf`` when it has none.

    A scanner reports "no return" as a code at the top of its range scale, so many readings sit on
    one or a few values there, far more than real returns put into any 1 cm bin nearby (SICK logs
    hold 81.83 m, 81.91 m, 50.00 m, or a band such as 51.05-51.16 m). Readings are binned at 1 cm; a
    bin is a *code* when it holds at least ``MIN_SHARE_AT_MAX`` of all readings (and 3) and
    ``SPIKE_RATIO`` times the mean count of the 1 cm bins in the ``BACKGROUND`` m below the band.
    The largest code, with fewer readings above it than a code holds, is the top of the band; every
    code within ``NO_RETURN_BAND`` below it belongs to the band, and the lowest is the no-return value
    (readings from it less ``MISS_MARGIN`` upwards are misses). Without such a code the log has no
    clipping value and every positive reading is a return.
    """
    values = readings[np.isfinite(readings) & (readings > 0)]
    if values.size == 0:
        return float("inf")
    levels, counts = np.unique(np.round(values * 100.0).astype(np.int64), return_counts=True)
    need = max(3.0, MIN_SHARE_AT_MAX * values.size)
    above = np.concatenate([np.cumsum(counts[::-1])[::-1][1:], [0]])  # readings in higher bins
    band = round(NO_RETURN_BAND * 100.0)

    def background(top: int) -> float:
        below = (levels >= top - band - round(BACKGROUND * 100.0)) & (levels < top - band)
        return float(counts[below].sum()) / (BACKGROUND * 100.0)

    candidates = np.flatnonzero((counts >= need) & (above < need))
    if candidates.size == 0:
        return float("inf")
    top = int(candidates[-1])
    threshold = max(need, SPIKE_RATIO * background(int(levels[top])))
    if counts[top] < threshold:
        return float("inf")
    codes = (levels >= levels[top] - band) & (levels <= levels[top]) & (counts >= threshold)
    return float(levels[codes].min()) / 100.0


def read_carmen(
    path: str | os.PathLike,
    message: str = "FLASER",
    max_range: float | None = None,
    sweep_s: float = SICK_SWEEP_S,
) -> Log:
    """Read every ``message`` line of a CARMEN log.

    Args:
        path: ``.log`` or ``.log.gz`` file.
        message: ``"FLASER"`` (front laser) or ``"RLASER"`` (rear laser).
        max_range: the sensor's no-return value (m); readings ``>= max_range - 1.5 cm`` are misses,
            and so are readings ``<= 0`` (a zero or negative range is how some drivers write "no
            return"). None detects it from the log (:func:`detect_max_range`).
        sweep_s: Time for the mirror to sweep the 180-degree field (s).

    Returns:
        A log of S scans of ``H = n`` beams x ``W = 1`` firing, world poses from the corrected pose
        fields; ``sensor["max_range_m"]`` holds the no-return value used (``inf``: none).

    Raises:
        LogFormatError: Missing, unreadable or corrupt file (or a folder), no ``message`` lines (other
            laser messages named), a line with the wrong number of fields, a non-numeric or non-finite
            value (line number and field named), or scans of different ``n`` (lines named).
    """
    path = Path(path)
    if path.is_dir():
        raise LogFormatError(f"{path}: is a folder; give the CARMEN log file in it (.log or .log.gz)")
    if not path.is_file():
        raise LogFormatError(f"{path}: no such CARMEN log")
    rows, widths, numbers, others = [], {}, [], {}
    for number, line in enumerate(text_lines(path), start=1):
        tokens = line.split()
        if not tokens or tokens[0] != message:
            if tokens and "LASER" in tokens[0]:
                others[tokens[0]] = others.get(tokens[0], 0) + 1
            continue
        try:
            values = parse_message(tokens, number)
        except LogFormatError as exc:
            raise LogFormatError(f"{path}: {exc}") from exc
        n = len(values) - 7
        rows.append(values)
        widths.setdefault(n, number)
        numbers.append(number)
    if not rows and others:
        found = ", ".join(f"{count} {name}" for name, count in sorted(others.items()))
        raise LogFormatError(
            f"{path}: no {message} messages, but {found} lines; mi-lidar reads {message} lines (n ranges, then "
            f"the laser's corrected pose x y theta): convert the laser lines to {message} lines"
        )
    if not rows:
        raise LogFormatError(f"{path}: no {message} messages; is this a CARMEN log?")
    if len(widths) != 1:
        (n_a, line_a), (n_b, line_b) = sorted(widths.items(), key=lambda item: item[1])[:2]
        raise LogFormatError(
            f"{path}: {message} scans have different beam counts {sorted(widths)} (line {line_a}: {n_a} beams, "
            f"line {line_b}: {n_b}); a log has one beam count: keep the scans of one count, or resample every "
            "scan to one count with tools/derive_carmen.py --beams N"
        )
    n = next(iter(widths))
    table = np.stack(rows)
    # Ranges are stored as float32: a reading beyond its range (3.4e38) is as bad as a NaN.
    finite = np.isfinite(table) & (np.abs(table) < np.where(np.arange(n + 7) < n, np.finfo(np.float32).max, np.inf))
    if not finite.all():
        scan, column = (int(i[0]) for i in np.nonzero(~finite))
        fields = ("x", "y", "theta", "odometry x", "odometry y", "odometry theta", "timestamp")
        if column < n:
            field, fix = f"range {column}", "write a no-return as the scanner's no-return value, or delete the line"
        else:
            field, fix = ("pose " * (column < n + 3)) + fields[column - n], "repair or delete the line"
        raise LogFormatError(
            f"{path}: line {numbers[scan]}: {message} {field} is {table[scan, column]:g}; ranges (below 3.4e38), "
            f"poses and timestamps must be finite numbers: {fix}"
        )
    readings, pose, odometry, stamp = table[:, :n], table[:, n : n + 3], table[:, n + 3 : n + 6], table[:, n + 6]
    if max_range is None:
        max_range = detect_max_range(readings)
    elif not max_range > 0:
        raise LogFormatError(f"{path}: max_range={max_range} m must be > 0 (the sensor's no-return value)")
    hit = (readings < max_range - MISS_MARGIN) & (readings > 0)
    angles = beam_angles(n)
    directions = np.stack([np.cos(angles), np.sin(angles), np.zeros(n)], axis=-1)[None, :, None]
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :2, 3] = pose[:, :2]
    times = stamp[:, None, None] + (np.arange(n) * sweep_s / n)[None, :, None]
    return Log(
        poses=poses,
        directions=directions,
        ranges=np.where(hit, readings, np.nan)[:, :, None],
        hit=hit[:, :, None],
        times=times,
        sensor={
            "name": f"carmen:{message}",
            "source": str(path),
            "max_range_m": float(max_range),
            "beam_angles_rad": angles.tolist(),
            "odometry": odometry.tolist(),
            "range_unit": "m",
        },
    )
