"""CARMEN planar laser logs (``FLASER`` / ``RLASER`` or ``ROBOTLASER1`` / ``ROBOTLASER2`` messages, plain or gzip)
-> :class:`~mi_lidar.core.log.Log`.

Two message layouts carry a scan with its pose (angles in rad, lengths in m, times in s):

- old laser, ``FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp``:
  ``x y theta`` is the (in corrected logs, SLAM-corrected) laser pose in the map frame; beam ``i``
  points at ``-pi/2 + i * pi / n`` in the laser frame (``pi / (n - 1)`` when ``n`` is odd, e.g. 181
  or 361 beams covering 180 deg inclusive) and is timed ``ipc_timestamp + i * sweep_s / n``;
- robot laser, ``ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range accuracy
  remission_mode n r_0 .. r_{n-1} m rem_0 .. rem_{m-1} laser_x laser_y laser_theta robot_x robot_y
  robot_theta tv rv forward_safety_dist side_safety_dist turn_axis ipc_timestamp host logger_timestamp``
  (GMapping ``.gfs.log`` outputs, Freiburg ``.clf`` logs): the laser pose is the scan's pose; beam ``i``
  points at ``start_angle + i * angular_resolution`` and is timed ``ipc_timestamp + i * |angular_resolution| *
  sweep_s / pi`` (the mirror turns at the rate of a SICK's 180 degrees in ``sweep_s``).

Each message becomes one scan of ``H = n`` beams by ``W = 1`` firing, so that per-beam quantities
(bias, angle offsets) are per row, as for every other sensor. The pose is the planar transform
(rotation ``theta`` about z, translation ``(x, y, 0)``). A reading at or above the sensor's
no-return value (less 1.5 cm) is a miss. That value is detected from the log
(:func:`detect_max_range`: the spike of readings at the top of the range scale: the SICK maximum
81.83 m in the Intel log, 50 m in logs that clip there, a band of codes such as 51.05-51.16 m or
81.83 and 81.91 m in others) or given as ``max_range``; the ``maximum_range`` field of a robot laser
line is the configured maximum, not necessarily that code, and is only kept in
``sensor['configured_max_range_m']``.

An old laser log keeps its raw odometry poses in ``sensor['odometry']`` (an (S, 3) list of x, y, theta).
A robot laser log keeps its robot poses in ``sensor['robot_pose']`` ((S, 3), x y theta) and no
``odometry`` (they are the robot's, not the laser's, and corrected or raw depending on the log), and
its remissions as ``attributes['intensity']`` ((S, n, 1) float32, the scanner's units) when every scan
carries one per beam; otherwise (none, or a count other than ``n`` on a line) they are dropped and
``sensor['remissions']`` says why.

:mod:`mi_lidar.io.carmen_lines` reads the fields of each line; this module assembles the scans into a log.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import (
    BeamAnglesWarning,
    DuplicateScanWarning,
    LogFormatError,
    NoReturnValueWarning,
    ParameterError,
    TimeOrderWarning,
    TruncatedLogWarning,
)
from mi_lidar.core.frames import MAX_COORDINATE_M
from mi_lidar.core.log import MAX_TIME_S, Log
from mi_lidar.io.carmen_lines import (
    BEAM_ANGLE_TOLERANCE,
    OLD_COLUMNS,
    ROBOT_COLUMNS,
    CutShort,
    RobotLaser,
    parse_message,
    parse_robot_laser,
)
from mi_lidar.io.text import text_lines

SICK_SWEEP_S = 1.0 / 150.0
MISS_MARGIN = 0.015  # m: readings this close to the no-return value are misses (the real-planar protocol)
MIN_SHARE_AT_MAX = 1e-3  # share of all readings a 1 cm bin must hold to be a no-return code
SPIKE_RATIO = 20.0  # a no-return code holds this many times the readings of a 1 cm bin just below it
NO_RETURN_BAND = 0.2  # m: no-return codes of one scanner lie within this band below the largest one
BACKGROUND = 5.0  # m: the readings this far below the codes give the background density of real returns
FLOAT32_MAX = float(np.finfo(np.float32).max)  # remissions are stored as float32
JITTER_S = 1.0  # s: a timestamp at most this far before the previous scan's is clock jitter (Intel log: up to 0.86 s)
MIN_REPEATED_RETURNS = 10  # a scan of this many returns repeated exactly is a copy (fewer: an open field, say)

OLD_LASER = ("FLASER", "RLASER")  # n ranges, then the laser pose, the odometry and the timestamp
KNOWN_FANS = (180, 181, 360, 361)  # beam counts of an old laser line whose angles are known (SICK LMS, 180 degrees)
ROBOT_LASER = ("ROBOTLASER1", "ROBOTLASER2")  # the laser's configuration, ranges, remissions, laser and robot poses


def beam_step(n: int) -> float:
    """The angle (rad) between neighbouring beams of an ``n``-beam 180-degree CARMEN scan (``FLASER``)."""
    return np.pi / (n - 1) if n % 2 else np.pi / n


def beam_angles(n: int) -> np.ndarray:
    """(n,) beam angles (rad) in the laser frame for an ``n``-beam 180-degree CARMEN scan, from -pi/2."""
    return -np.pi / 2 + np.arange(n) * beam_step(n)


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


def default_message(lines: list[str]) -> str:
    """``FLASER`` when a line holds one (the scoring protocol reads them), else ``ROBOTLASER1`` when a line does,
    else ``FLASER`` (named in the refusal)."""
    for name in ("FLASER", "ROBOTLASER1"):
        if any(map(re.compile(rf"\s*{name}\s").match, lines)):  # stops at the first such line
            return name
    return "FLASER"


def read_carmen(
    path: str | os.PathLike,
    message: str | None = None,
    max_range: float | None = None,
    sweep_s: float = SICK_SWEEP_S,
) -> Log:
    """Read every ``message`` line of a CARMEN log.

    Args:
        path: ``.log``, ``.clf`` or ``.log.gz`` file.
        message: ``"FLASER"`` (front laser), ``"RLASER"`` (rear laser), ``"ROBOTLASER1"`` or ``"ROBOTLASER2"``
            (robot laser messages of the first and second laser). None: ``FLASER`` when the log has any,
            else ``ROBOTLASER1``.
        max_range: the sensor's no-return value (m); readings ``>= max_range - 1.5 cm`` are misses,
            and so are readings ``<= 0`` (a zero or negative range is how some drivers write "no
            return"). None detects it from the log (:func:`detect_max_range`).
        sweep_s: Time for the mirror to sweep 180 degrees (s).

    Returns:
        A log of S scans of ``H = n`` beams x ``W = 1`` firing, world poses from the corrected (laser) pose
        fields; ``sensor["max_range_m"]`` holds the no-return value used (``inf``: none) and
        ``sensor["beam_angles_rad"]`` the n beam angles in the laser frame (see the module docstring for
        the rest of ``sensor`` and the remissions).

    Raises:
        ParameterError: a ``message`` mi-lidar does not read.
        LogFormatError: Missing, unreadable or corrupt file (or a folder), no ``message`` lines (other
            laser messages named), a line with the wrong number of fields (but the file's last line, cut short
            by a logger stopped mid-write, is skipped with a :class:`~mi_lidar.core.errors.TruncatedLogWarning`,
            as is the end of a gzip stream cut short), a non-numeric or non-finite value, a range beyond 1e8 m
            or a timestamp beyond 1e11 s (line number and field named), or scans of different ``n`` or, for robot
            laser lines, of different beam angles (lines named).

    Warns:
        NoReturnValueWarning: a given ``max_range`` below returns of the log (readings below the no-return value it
            detects) or above that value: they are read as no-returns, or its no-returns as returns.
        TimeOrderWarning: a timestamp more than :data:`JITTER_S` before the previous scan's (lines and times named);
            the scans are read as written. Smaller steps back (clock corrections) are read silently.
        DuplicateScanWarning: scans that repeat the previous scan exactly (readings and laser pose; at least
            :data:`MIN_REPEATED_RETURNS` returns): they are dropped, so the log has fewer scans than lines.
        BeamAnglesWarning: old laser scans of a beam count other than :data:`KNOWN_FANS`: their angles, spread over
            180 degrees, are a guess.
    """
    path = Path(path)
    if path.is_dir():
        raise LogFormatError(f"{path}: is a folder; give the CARMEN log file in it (.log or .log.gz)")
    if not path.is_file():
        raise LogFormatError(f"{path}: no such CARMEN log")
    lines = text_lines(path)
    wanted = message or "FLASER or ROBOTLASER1"
    message = message or default_message(lines)
    if message not in OLD_LASER + ROBOT_LASER:
        raise ParameterError(
            f"message={message!r}: mi-lidar reads the laser messages with a pose, {', '.join(OLD_LASER + ROBOT_LASER)}"
        )
    robot = message in ROBOT_LASER
    rows, widths, numbers, others, scans = [], {}, [], {}, []
    last = next((k for k in range(len(lines), 0, -1) if lines[k - 1].strip()), 0)  # the last line with text
    for number, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0] != message:
            if tokens and "LASER" in tokens[0]:
                others[tokens[0]] = others.get(tokens[0], 0) + 1
            continue
        try:
            if robot:
                scans.append(parse_robot_laser(tokens, number))
            values = scans[-1].values if robot else parse_message(tokens, number)
        except CutShort as exc:
            if number != last or not rows:  # a short line before the end is damage; a log of one line is refused
                raise LogFormatError(f"{path}: {exc}") from exc
            warnings.warn(
                f"{path}: line {number}, the last, is a {message} line cut short ({len(tokens)} fields, fewer than "
                f"its counts need: a logger stopped mid-write?): read the {len(rows)} complete scans before it; "
                "delete the line to silence this warning",
                TruncatedLogWarning,
                stacklevel=2,
            )
            continue
        except LogFormatError as exc:
            raise LogFormatError(f"{path}: {exc}") from exc
        n = len(values) - 7
        rows.append(values)
        widths.setdefault(n, number)
        numbers.append(number)
    if not rows and others:
        found = ", ".join(f"{count} {name}" for name, count in sorted(others.items()))
        readable = [name for name in sorted(others) if name in OLD_LASER + ROBOT_LASER]
        fix = (
            f"read them with --message {readable[0]} (from Python: message={readable[0]!r})"
            if readable
            else f"convert the laser lines to {wanted} lines"
        )
        raise LogFormatError(
            f"{path}: no {wanted} messages, but {found} lines; mi-lidar reads the laser lines that carry the laser's "
            f"corrected pose (FLASER, RLASER, ROBOTLASER1, ROBOTLASER2): {fix}"
        )
    if not rows:
        raise LogFormatError(f"{path}: no {wanted} messages; is this a CARMEN log?")
    if len(widths) != 1:
        (n_a, line_a), (n_b, line_b) = sorted(widths.items(), key=lambda item: item[1])[:2]
        fix = "split the log" if robot else "resample every scan to one count with tools/derive_carmen.py --beams N"
        raise LogFormatError(
            f"{path}: {message} scans have different beam counts {sorted(widths)} (line {line_a}: {n_a} beams, "
            f"line {line_b}: {n_b}); a log has one beam count: keep the scans of one count, or {fix}"
        )
    n = next(iter(widths))
    table = np.stack(rows)
    _check_values(path, message, table, numbers, ROBOT_COLUMNS if robot else OLD_COLUMNS)
    detected = detect_max_range(table[:, :n])
    if max_range is None:
        max_range = detected
    elif not max_range > 0:
        raise LogFormatError(f"{path}: max_range={max_range} m must be > 0 (the sensor's no-return value)")
    else:
        _check_given_max_range(path, table[:, :n], max_range, detected)
    hit = (table[:, :n] < max_range - MISS_MARGIN) & (table[:, :n] > 0)
    keep = _unrepeated(path, message, table[:, : n + 3], hit, numbers)
    table, hit, numbers = table[keep], hit[keep], [number for number, kept in zip(numbers, keep) if kept]
    scans = [scan for scan, kept in zip(scans, keep) if kept] if robot else scans
    readings, pose, other_pose, stamp = table[:, :n], table[:, n : n + 3], table[:, n + 3 : n + 6], table[:, n + 6]
    _check_time_order(path, message, stamp, numbers)
    sensor = {"name": f"carmen:{message}", "source": str(path), "max_range_m": float(max_range)}
    attributes = {}
    if robot:
        angles = _robot_angles(path, message, scans, numbers)
        offsets = np.arange(n) * abs(scans[0].step) * sweep_s / np.pi
        intensity, sensor["remissions"] = _intensity(path, message, scans, numbers)
        if intensity is not None:
            attributes["intensity"] = intensity[:, :, None]
        sensor["configured_max_range_m"] = scans[0].configured_max_range
        sensor["robot_pose"] = other_pose.tolist()
    else:
        angles, offsets = beam_angles(n), np.arange(n) * sweep_s / n
        sensor["odometry"] = other_pose.tolist()
        _check_fan(path, message, n, numbers[0])
    directions = np.stack([np.cos(angles), np.sin(angles), np.zeros(n)], axis=-1)[None, :, None]
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :2, 3] = pose[:, :2]
    return Log(
        poses=poses,
        directions=directions,
        ranges=np.where(hit, readings, np.nan)[:, :, None],
        hit=hit[:, :, None],
        times=stamp[:, None, None] + offsets[None, :, None],
        attributes=attributes,
        sensor={**sensor, "beam_angles_rad": angles.tolist(), "range_unit": "m"},
    )


def _check_values(path: Path, message: str, table: np.ndarray, numbers: list[int], columns: tuple[str, ...]) -> None:
    """Refuse a value of the (S, n + 7) ``table`` of ranges, poses and timestamps that no measurement has, naming its
    line (from ``numbers``) and its field (``range i`` or one of the 7 ``columns``): a non-finite number, a range
    beyond :data:`~mi_lidar.core.frames.MAX_COORDINATE_M` or a timestamp beyond :data:`~mi_lidar.core.log.MAX_TIME_S`
    (limits that :meth:`~mi_lidar.core.log.Log.check_values` holds every log to, here with the line named and
    before the no-return value is detected or the time order checked). Pose positions are checked with the poses
    (:func:`~mi_lidar.core.poses.validate_poses`)."""
    n = table.shape[1] - len(columns)
    limit = np.full(table.shape[1], np.inf)
    limit[:n], limit[n + 6] = MAX_COORDINATE_M, MAX_TIME_S
    good = np.isfinite(table) & (np.abs(table) <= limit)
    if good.all():
        return
    scan, column = (int(i[0]) for i in np.nonzero(~good))
    value = table[scan, column]
    if column < n:
        field, rule = f"range {column}", f"ranges are finite numbers of metres below {MAX_COORDINATE_M:.0e} m"
        fix = "write a no-return as the scanner's no-return value, or delete the line"
    elif column == n + 6:
        field, rule = columns[column - n], f"timestamps are finite seconds within {MAX_TIME_S:.0e} s of 1970"
        fix = "write them in seconds (not ms, us or ns), or repair or delete the line"
    else:
        field, rule, fix = columns[column - n], "poses are finite numbers", "repair or delete the line"
    farther = " (a larger one is a misread number)" if np.isfinite(value) else ""
    raise LogFormatError(f"{path}: line {numbers[scan]}: {message} {field} is {value:g}; {rule}{farther}: {fix}")


def _check_given_max_range(path: Path, readings: np.ndarray, max_range: float, detected: float) -> None:
    """Warn when the given no-return value ``max_range`` (m) disagrees with the (S, n) ``readings``: when it lies more
    than :data:`MISS_MARGIN` below readings that the log's own no-return value ``detected`` (m; ``inf``: none) makes
    returns, or above that value, so that its no-return codes are read as returns (how many, where, and what the log
    holds). Readings at the value given are its code, not returns (a log too short for the code to be detected)."""
    code = f"the log's no-return value is {detected:g} m" if np.isfinite(detected) else "the log has no no-return value"
    given = f"{path}: max_range={max_range:g} m"
    fix = "give the sensor's no-return value (--max-range), or leave it out to detect it from the log"
    cut = (readings > max_range + MISS_MARGIN) & (readings < detected - MISS_MARGIN)  # not at the code given
    if cut.any():
        warnings.warn(
            f"{given} lies below {np.count_nonzero(cut):,} returns of the log ({np.mean(cut):.1%} of its readings, "
            f"{readings[cut].min():g} to {readings[cut].max():g} m; {code}), which are read as no-returns: "
            f"{fix}",
            NoReturnValueWarning,
            stacklevel=3,
        )
    kept = (readings >= detected - MISS_MARGIN) & (readings < max_range - MISS_MARGIN)
    if kept.any():
        warnings.warn(
            f"{given} lies above the log's no-return value {detected:g} m, so its {np.count_nonzero(kept):,} "
            f"no-return readings ({np.mean(kept):.1%} of its readings) are read as returns at {detected:g} m and up: "
            f"{fix}",
            NoReturnValueWarning,
            stacklevel=3,
        )


def _check_time_order(path: Path, message: str, stamp: np.ndarray, numbers: list[int]) -> None:
    """Warn when a scan's timestamp in ``stamp`` (S,) is more than :data:`JITTER_S` before the previous scan's,
    naming the first such step (lines from ``numbers``, both times) and how many there are."""
    back = np.flatnonzero(np.diff(stamp) < -JITTER_S)
    if back.size == 0:
        return
    a, b = int(back[0]), int(back[0]) + 1
    more = f" (and {back.size - 1} more such steps)" if back.size > 1 else ""
    warnings.warn(
        f"{path}: line {numbers[b]}: {message} timestamp {stamp[b]:.3f} s is {stamp[a] - stamp[b]:.3f} s before line "
        f"{numbers[a]}'s {stamp[a]:.3f} s{more}: a step back beyond clock jitter ({JITTER_S:g} s), concatenated "
        "logs? Time windows compare timestamps, so benchmark-planar's leave-out maps (the scans within 1 m and 30 s "
        "of a scan, --radius, --window) misjudge which scans are neighbours across it: split the log at line "
        f"{numbers[b]} or make its timestamps increase",
        TimeOrderWarning,
        stacklevel=3,
    )


def _unrepeated(path: Path, message: str, scans: np.ndarray, hit: np.ndarray, numbers: list[int]) -> np.ndarray:
    """(S,) True for the scans to keep: False where a scan's readings and laser pose (the (S, n + 3) ``scans``) equal
    the previous scan's exactly and it has at least :data:`MIN_REPEATED_RETURNS` returns (``hit``, (S, n)); warns
    once, naming the first such line (from ``numbers``) and how many were dropped.

    A copy of a scan (a logger that wrote a line twice, a stalled driver repeating its last scan at a new timestamp)
    would put a copy of a test scan among benchmark-planar's training scans. A repeated scan of (almost) no returns
    is kept: an open field looks the same from one moment to the next.
    """
    repeat = np.concatenate([[False], (scans[1:] == scans[:-1]).all(axis=1)])
    repeat &= hit.sum(axis=1) >= MIN_REPEATED_RETURNS
    if repeat.any():
        first = int(np.argmax(repeat))
        dropped = int(repeat.sum())
        warnings.warn(
            f"{path}: line {numbers[first]}: {message} scan repeats line {numbers[first - 1]}'s exactly (the same "
            f"{int(hit[first].sum())} returns at the same pose: a line written twice, or a stalled driver?); dropped "
            f"{dropped} such repeated scan{'s' if dropped > 1 else ''} of {len(scans)}, so that no copy of a test scan "
            "trains benchmark-planar's models. Nothing to do: the copies were dropped; de-duplicate the log to "
            "silence this warning",
            DuplicateScanWarning,
            stacklevel=3,
        )
    return ~repeat


def _check_fan(path: Path, message: str, n: int, number: int) -> None:
    """Warn when old laser scans of ``n`` beams (the first on line ``number``) have a count whose angles are a guess:
    their lines give no field of view, and :func:`beam_angles` spreads them over 180 degrees."""
    if n in KNOWN_FANS:
        return
    warnings.warn(
        f"{path}: line {number}: {message} scans of {n} beams; a {message} line gives no field of view, and mi-lidar "
        f"knows the beam angles of {', '.join(map(str, KNOWN_FANS))} beams (180 degrees), so these are read over 180 "
        f"degrees from -90, a beam every {np.degrees(beam_step(n)):.4g} deg. A scanner that covers another angle "
        "(541 or 1081 beams: usually 270 degrees) is read wrong: write its scans as ROBOTLASER1 lines, which give "
        "start_angle and angular_resolution",
        BeamAnglesWarning,
        stacklevel=3,
    )


def _robot_angles(path: Path, message: str, scans: list[RobotLaser], numbers: list[int]) -> np.ndarray:
    """(n,) beam angles (rad) of robot laser ``scans`` of n beams, refusing (lines named) scans whose beams point
    more than :data:`BEAM_ANGLE_TOLERANCE` away from the first scan's."""
    n = len(scans[0].values) - 7
    starts, steps = np.array([(scan.start, scan.step) for scan in scans]).T
    apart = np.abs(starts - starts[0]) + (n - 1) * np.abs(steps - steps[0])  # the largest angle between two beams
    if (apart > BEAM_ANGLE_TOLERANCE).any():
        k = int(np.argmax(apart > BEAM_ANGLE_TOLERANCE))

        def pattern(i: int) -> str:
            return f"line {numbers[i]}: start_angle {starts[i]:g} rad, angular_resolution {steps[i]:g} rad"

        raise LogFormatError(
            f"{path}: {message} scans have different beam angles ({pattern(0)}; {pattern(k)}); a log has one beam "
            "pattern: keep the scans of one pattern (split the log)"
        )
    return starts[0] + np.arange(n) * steps[0]


def _intensity(path: Path, message: str, scans: list[RobotLaser], numbers: list[int]) -> tuple[np.ndarray | None, str]:
    """The (S, n) remissions of robot laser ``scans`` when each carries one per beam (else None), and a word on them.

    Raises:
        LogFormatError: a kept remission that is not a finite float32 (line and remission named).
    """
    n = len(scans[0].values) - 7
    odd = next((i for i, scan in enumerate(scans) if len(scan.remissions) != n), None)
    if odd is not None:
        m = len(scans[odd].remissions)
        none = all(len(scan.remissions) == 0 for scan in scans)
        return None, "none in the log" if none else f"dropped: line {numbers[odd]} has {m} for {n} beams"
    table = np.stack([scan.remissions for scan in scans])
    bad = ~(np.abs(table) < FLOAT32_MAX)
    if bad.any():
        scan, beam = (int(i) for i in np.argwhere(bad)[0])
        raise LogFormatError(
            f"{path}: line {numbers[scan]}: {message} remission {beam} is {table[scan, beam]:g}; remissions must be "
            "finite numbers (below 3.4e38): repair or delete the line"
        )
    return table.astype(np.float32), "kept as attributes['intensity']"
