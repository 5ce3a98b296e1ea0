"""The fields of one CARMEN laser line (``FLASER`` / ``RLASER`` or ``ROBOTLASER1`` / ``ROBOTLASER2``), the
layouts that :mod:`mi_lidar.io.carmen` reads (its docstring gives them and what the fields mean).

:func:`parse_message` reads an old laser line and :func:`parse_robot_laser` a robot laser line into the
(n + 7,) values a scan keeps: its n ranges, then the 7 fields of :data:`OLD_COLUMNS` or :data:`ROBOT_COLUMNS`.
Both refuse a line whose counts and fields disagree, or a field that is not a number, naming the line and the
field; a line with fewer fields than its counts need raises :class:`CutShort`, which
:func:`~mi_lidar.io.carmen.read_carmen` skips with a warning when it is the file's last.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from mi_lidar.core.errors import LogFormatError

BEAM_ANGLE_TOLERANCE = 1e-3  # rad: robot laser scans whose beams point this close to the first scan's share its pattern

# the fields of an old laser line a scan keeps besides its ranges
OLD_COLUMNS = ("pose x", "pose y", "pose theta", "odometry x", "odometry y", "odometry theta", "timestamp")
ROBOT_COLUMNS = tuple(  # the fields of a robot laser line a scan keeps besides its ranges
    "laser_pose_x laser_pose_y laser_pose_theta robot_pose_x robot_pose_y robot_pose_theta timestamp".split()
)
ROBOT_HEAD = tuple(  # the fields of a robot laser line before its ranges
    "laser_type start_angle field_of_view angular_resolution maximum_range accuracy remission_mode num_readings".split()
)
ROBOT_TAIL = ROBOT_COLUMNS[:6] + tuple(  # the fields after its remissions
    "laser_tv laser_rv forward_safety_dist side_safety_dist turn_axis timestamp host logger_timestamp".split()
)


class CutShort(LogFormatError):
    """A laser line ends before the fields its counts announce (read_carmen skips it when it is the file's last)."""


def parse_message(tokens: list[str], number: int) -> np.ndarray:
    """The (n + 7,) values of one laser line's ``tokens`` (``NAME n ranges... x y theta odom_x odom_y
    odom_theta timestamp host logger_timestamp``): its n ranges, pose, odometry and timestamp.

    Raises:
        LogFormatError: a beam count below 2, a non-numeric value (field named), too few fields, or more than the
            count allows (``n`` smaller than the ranges given) (``number``: the line's number, named in the message).
    """
    name = tokens[0]
    try:
        n = int(tokens[1])
        if n <= 1:
            raise ValueError(f"beam count {n} must be > 1")
        _check_length(tokens, number, n + 10, f"n={n}", "n ranges + 10", f"the beam count {n}")  # before the values
    except IndexError:
        raise CutShort(f"line {number}: {name} ends after its name: truncated: repair or delete the line") from None
    except ValueError as exc:
        raise LogFormatError(f"line {number}: malformed {name} message ({exc}): repair or delete the line") from exc
    numeric = tokens[2 : 2 + n + 7]  # the ranges, the pose, the odometry and the timestamp
    try:
        return np.array(numeric, dtype=np.float64)
    except ValueError:
        k = next(k for k, token in enumerate(numeric) if not _is_number(token))
    field = f"range {k}" if k < n else OLD_COLUMNS[k - n]
    # the host name where the timestamp belongs, the logger timestamp last: one value is missing before it
    short = k == n + 6 and len(tokens) == n + 10 and _is_number(tokens[-1])
    why = f": the line holds one value fewer than n={n} ranges and 7 fields need (a value lost, or n is wrong)"
    raise LogFormatError(
        f"line {number}: malformed {name} message: {field} is {numeric[k]!r}, not a number{why if short else ''}: "
        "repair or delete the line"
    )


def _check_length(tokens: list[str], number: int, need: int, counts: str, rule: str, count: str) -> None:
    """Refuse line ``number`` when its ``tokens`` are fewer than ``need`` or more than ``need`` and a logger
    timestamp (``counts``: the counts read, ``rule``: how they make ``need``, ``count``: the count to repair)."""
    name = tokens[0]
    if len(tokens) < need:
        raise CutShort(
            f"line {number}: {name} with {counts} needs {need} fields ({rule}); found {len(tokens)} (truncated?): "
            "repair or delete the line"
        )
    if len(tokens) > need + 1 or (len(tokens) == need + 1 and not _is_number(tokens[-1])):
        raise LogFormatError(
            f"line {number}: {name} with {counts} has {len(tokens)} fields, where {rule} (one more with the logger "
            f"timestamp) make {need} or {need + 1}: {count} is smaller than the values on the line; repair the count "
            "or delete the line"
        )


class RobotLaser(NamedTuple):
    """The fields of one ``ROBOTLASER1`` line that a scan needs."""

    start: float  # rad: angle of beam 0 in the laser frame
    step: float  # rad: angle between neighbouring beams (the angular_resolution field)
    configured_max_range: float  # m: the maximum_range field (not necessarily the no-return code)
    values: np.ndarray  # (n + 7,): n ranges, laser pose x y theta, robot pose x y theta, timestamp
    remissions: np.ndarray  # (m,): the m remissions (m = 0 when the line has none)


def robot_field(k: int, n: int, m: int) -> str:
    """The name of token ``k`` (1: the first after the message name) of a robot laser line of n ranges, m remissions."""
    if k <= len(ROBOT_HEAD):
        return ROBOT_HEAD[k - 1]
    if k < 9 + n:
        return f"range {k - 9}"
    if k == 9 + n:
        return "num_remissions"
    if k < 10 + n + m:
        return f"remission {k - 10 - n}"
    return ROBOT_TAIL[k - 10 - n - m]


def _count(tokens: list[str], k: int, n: int, low: int, number: int) -> int:
    """The whole number in token ``k`` (num_readings or num_remissions) of a robot laser line, at least ``low``."""
    name, field = tokens[0], robot_field(k, n, 0)
    if k >= len(tokens):
        raise CutShort(
            f"line {number}: {name} ends before {field} (field {k}; the line has {len(tokens)}): truncated"
            + (f", or num_readings {n} is larger than the ranges on the line" if k > 8 else "")
            + ": repair or delete the line"
        )
    try:
        count = int(tokens[k])
    except ValueError:
        raise LogFormatError(
            f"line {number}: malformed {name} message: {field} is {tokens[k]!r}, not a whole number: repair or "
            "delete the line"
        ) from None
    if count < low:
        raise LogFormatError(
            f"line {number}: {name} {field} is {count}; it must be >= {low}: repair or delete the line"
        )
    return count


def parse_robot_laser(tokens: list[str], number: int) -> RobotLaser:
    """The fields of one robot laser line's ``tokens`` (``ROBOTLASER1 laser_type start_angle ... num_readings
    ranges... num_remissions remissions... laser pose, robot pose, tv rv safety distances turn_axis timestamp host
    logger_timestamp``; the logger timestamp may be missing).

    Raises:
        LogFormatError: a beam count below 2 or a negative remission count, a non-numeric value (field named), too
            few fields (truncated, or a num_remissions that overruns the line), more than the counts allow, or a
            beam pattern that is not one (non-finite start angle or resolution, a zero step, beams spanning more
            than a turn) (``number``: the line's number, named in the message).
    """
    name = tokens[0]
    n = _count(tokens, 8, 0, 2, number)
    m = _count(tokens, 9 + n, n, 0, number)
    need = n + m + 23  # the name, 8 config fields, n ranges, num_remissions, m remissions, 13 fields after them
    counts = f"num_readings={n}, num_remissions={m}"
    if m and need - m <= len(tokens) < need:
        raise CutShort(
            f"line {number}: {name} num_remissions {m} overruns the line: with {counts} it needs {need} fields "
            f"(13 after the remissions), found {len(tokens)}: a wrong remission count or a line cut short: repair "
            "num_remissions (0 when the line has no remissions) or delete the line"
        )
    _check_length(
        tokens, number, need, counts, "n ranges + m remissions + 23", f"num_readings {n} or num_remissions {m}"
    )
    numeric = tokens[1 : need - 1]  # all but the host (and the logger timestamp)
    try:
        values = np.array(numeric, dtype=np.float64)
    except ValueError:
        k = next(k for k, token in enumerate(numeric, start=1) if not _is_number(token))
        raise LogFormatError(
            f"line {number}: malformed {name} message: {robot_field(k, n, m)} is {tokens[k]!r}, not a number: "
            "repair or delete the line"
        ) from None
    start, step, configured = values[1], values[3], values[4]
    for field, value in (("start_angle", start), ("angular_resolution", step)):
        if not np.isfinite(value):
            raise LogFormatError(
                f"line {number}: {name} {field} is {value:g}; beam angles need finite numbers (rad): repair or "
                "delete the line"
            )
    span = abs(step) * (n - 1)
    if step == 0 or span > 2 * np.pi + BEAM_ANGLE_TOLERANCE:
        raise LogFormatError(
            f"line {number}: {name} angular_resolution {step:g} rad puts its {n} beams over {np.degrees(span):g} "
            f"deg; the beams need distinct angles within one turn (angles in degrees where radians belong?): "
            "repair or delete the line"
        )
    tail = values[9 + n + m :]  # laser pose, robot pose, tv rv forward/side safety distances turn_axis, timestamp
    return RobotLaser(
        start=float(start),
        step=float(step),
        configured_max_range=float(configured),
        values=np.concatenate([values[8 : 8 + n], tail[:6], tail[11:12]]),
        remissions=values[9 + n : 9 + n + m],
    )


def _is_number(token: str) -> bool:
    """Whether ``token`` reads as a float."""
    try:
        float(token)
    except ValueError:
        return False
    return True
