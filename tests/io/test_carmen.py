import errno
import gzip
import warnings
from pathlib import Path

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError, NoReturnValueWarning, ParameterError, TimeOrderWarning
from mi_lidar.io import read_any, read_carmen
from mi_lidar.io.carmen import beam_angles, detect_max_range

from .conftest import data_file
from .synth import carmen_text


def test_real_intel_log():
    log = read_carmen(data_file("carmen/intel-corrected.log.gz"))
    assert log.shape == (910, 180, 1)
    assert log.sensor["max_range_m"] == pytest.approx(81.83)
    assert (~log.hit).sum() == 4172
    assert np.all(np.isnan(log.ranges[~log.hit]))
    assert 0.2 < np.nanmin(log.ranges) and np.nanmax(log.ranges) < 26.0
    np.testing.assert_allclose(log.poses[0, :2, 3], [0.600266, -0.0320327])
    np.testing.assert_allclose(np.arctan2(log.poses[0, 1, 0], log.poses[0, 0, 0]), -0.354665)
    world = log.poses[0, :3, :3] @ log.directions[0, 0, 0]
    np.testing.assert_allclose(np.arctan2(world[1], world[0]), -0.354665 - np.pi / 2)
    assert np.sum(np.diff(log.times[:, 0, 0]) < 0) == 4  # the log itself has 4 small timestamp reversals
    # Indoor lab: every world point stays inside the ~40 m building.
    points = log.points_world()[log.hit]
    assert np.ptp(points[:, 0]) < 45 and np.ptp(points[:, 1]) < 45


def test_synthetic_plain_and_gzip(tmp_path):
    text = carmen_text(scans=3)
    (tmp_path / "a.log").write_text(text)
    (tmp_path / "a.log.gz").write_bytes(gzip.compress(text.encode()))
    plain, packed = read_carmen(tmp_path / "a.log"), read_any(tmp_path / "a.log.gz")
    np.testing.assert_array_equal(plain.ranges, packed.ranges)
    assert plain.shape == (3, 180, 1)
    assert not plain.hit[:, 5, 0].any() and plain.hit.sum() == 3 * 179
    np.testing.assert_allclose(plain.ranges[0, 10, 0], 1.10)
    np.testing.assert_allclose(plain.poses[2, :2, 3], [2.0, 2.0])
    np.testing.assert_allclose(plain.times[1, 0, 0], 11.0)
    np.testing.assert_allclose(plain.times[1, 179, 0] - plain.times[1, 0, 0], 179 / 180 / 150)


def test_beam_layout():
    np.testing.assert_allclose(np.degrees(beam_angles(180))[[0, 1, -1]], [-90, -89, 89])
    np.testing.assert_allclose(np.degrees(beam_angles(361))[[0, 1, -1]], [-90, -89.5, 90])


@pytest.mark.parametrize(
    "line, message",
    [
        ("FLASER 3 1 2", "line 2: FLASER with n=3 needs 13 fields"),
        # a count larger than the ranges read the host name as a number: "could not convert string to float: 'host'"
        (
            "FLASER 99 1 2 3 0 0 0 0 0 0 5 host 5",
            r"line 2: FLASER with n=99 needs 109 fields \(n ranges \+ 10\); found 14",
        ),
        (
            "FLASER 3 1 2 x 0 0 0 0 0 0 5 host 5",
            "line 2: malformed FLASER message: range 2 is 'x', not a number: repair",
        ),
        (
            "FLASER 3 1 2 3 0 0 y 0 0 0 5 host 5",
            "line 2: malformed FLASER message: pose theta is 'y', not a number: re",
        ),
        # a value lost (here range 2): the host name was read as the timestamp, 'could not convert string to float:
        # 'host'', with no field or cause named
        (
            "FLASER 3 1 2 0 0 0 0 0 0 5 host 5",
            r"line 2: malformed FLASER message: timestamp is 'host', not a number: the line holds one value fewer "
            r"than n=3 ranges and 7 fields need \(a value lost, or n is wrong\): repair or delete the line",
        ),
        ("FLASER 3 1 2 nan 0 0 0 0 0 0 5 host 5", "line 2: FLASER range 2 is nan"),
        # a count smaller than the ranges read the surplus ranges as the pose, silently
        (
            "FLASER 2 1 2 3 0 0 0 0 0 0 5 host 5",
            r"line 2: FLASER with n=2 has 14 fields, .* make 12 or 13: the beam count",
        ),
        ("FLASER 2 1 2 3 0 0 0 0 0 0 5 host", r"line 2: FLASER with n=2 has 13 fields, .* count 2 is smaller than"),
    ],
)
def test_malformed_lines(tmp_path, line, message):
    (tmp_path / "bad.log").write_text("# header\n" + line + "\n")
    with pytest.raises(LogFormatError, match=message):
        read_carmen(tmp_path / "bad.log")


def test_a_line_without_the_logger_timestamp_reads(tmp_path):
    (tmp_path / "short.log").write_text("FLASER 3 1 2 3 0.5 0 0 0 0 0 5 host\n")
    log = read_carmen(tmp_path / "short.log", max_range=80.0)
    np.testing.assert_allclose(log.ranges[0, :, 0], [1, 2, 3])
    np.testing.assert_allclose(log.poses[0, 0, 3], 0.5)


def test_empty_and_mixed_logs(tmp_path):
    (tmp_path / "empty.log").write_text("ODOM 0 0 0 0 0 0 1 host 1\n")
    with pytest.raises(LogFormatError, match="no FLASER or ROBOTLASER1 messages; is this a CARMEN log"):
        read_carmen(tmp_path / "empty.log")
    with pytest.raises(LogFormatError, match="no RLASER messages; is this a CARMEN log"):
        read_carmen(tmp_path / "empty.log", message="RLASER")
    (tmp_path / "mixed.log").write_text(carmen_text(1, 180) + carmen_text(1, 181))
    with pytest.raises(LogFormatError, match=r"different beam counts \[180, 181\] \(line 4: 180 beams, line 8: 181\)"):
        read_carmen(tmp_path / "mixed.log")
    packed = bytearray(gzip.compress(carmen_text().encode()))
    packed[3] = 0xE0  # reserved header flags set: no gzip writer does that
    (tmp_path / "t.log.gz").write_bytes(bytes(packed))
    with pytest.raises(LogFormatError, match="t.log.gz: corrupt gzip stream .*; recompress the log"):
        read_carmen(tmp_path / "t.log.gz")


def test_no_return_codes_of_real_scanners_are_detected():
    """SICK logs carry one or several no-return codes at the top of the scale, above or among real returns."""
    rng = np.random.default_rng(1)
    indoor = rng.uniform(0.5, 30.0, 20_000)
    # a band of codes (as in logs clipping near 51 m): every reading from the lowest code up is a miss
    band = np.concatenate([indoor, np.full(300, 51.06), np.full(60, 51.11), np.full(2, 51.16)])
    assert detect_max_range(band) == pytest.approx(51.06)
    # a stray reading above the code does not hide it
    assert detect_max_range(np.concatenate([band, [51.25]])) == pytest.approx(51.06)
    # outdoors, real returns reach the top of the scale; two codes (81.83 and 81.91 m) sit on them
    outdoor = np.concatenate([rng.uniform(0.5, 81.8, 20_000), np.full(400, 81.83), np.full(3000, 81.91)])
    assert detect_max_range(outdoor) == pytest.approx(81.83)
    # a busy range bin near the top of a log without codes is not a code
    assert detect_max_range(np.concatenate([indoor, rng.normal(29.5, 0.005, 25)])) == np.inf


def test_max_range_detected_or_given(tmp_path):
    rng = np.random.default_rng(0)
    readings = rng.uniform(0.5, 30.0, 5000)
    assert detect_max_range(readings) == np.inf  # no value that many readings sit on: no clipping
    readings[:40] = 50.0  # a scanner that clips at 50 m
    assert detect_max_range(readings) == 50.0
    text = carmen_text(scans=3, max_range=50.0)
    (tmp_path / "c.log").write_text(text)
    log = read_carmen(tmp_path / "c.log")
    assert log.sensor["max_range_m"] == 50.0 and not log.hit[:, 5, 0].any()
    with pytest.warns(NoReturnValueWarning, match="max_range=100 m lies above the log's no-return value 50 m"):
        given = read_carmen(tmp_path / "c.log", max_range=100.0)  # the user says the sensor reaches 100 m
    assert given.hit[:, 5, 0].all() and np.allclose(given.ranges[:, 5, 0], 50.0)
    with pytest.raises(LogFormatError, match="max_range=-1.0 m must be > 0"):
        read_carmen(tmp_path / "c.log", max_range=-1.0)


@pytest.mark.filterwarnings("error")  # the log's own no-return value, given: no warning
@pytest.mark.parametrize(
    "max_range, said",
    [
        (
            2.0,  # a SICK log with returns up to 2.79 m and 81.83 m codes, given a 2 m no-return value
            r"max_range=2 m lies below 234 returns of the log \(43.3% of its readings, 2.02 to 2.79 m; the log's "
            r"no-return value is 81.83 m\), which are read as no-returns: give the sensor's no-return value",
        ),
        (
            100.0,
            r"max_range=100 m lies above the log's no-return value 81.83 m, so its 3 no-return readings \(0.6% of its "
            r"readings\) are read as returns at 81.83 m and up: give the sensor's no-return value \(--max-range\), or",
        ),
        (81.83, None),
    ],
)
def test_a_given_no_return_value_that_disagrees_with_the_log_is_warned(tmp_path, max_range, said):
    """--max-range 5 on a log of returns up to 10.65 m read 37 % of its readings as no-returns without a word (and
    --max-range 100 on Intel read its 4,172 no-returns as returns at 81.83 m); what is read stays as given."""
    (tmp_path / "c.log").write_text(carmen_text(scans=3))
    if said is None:
        log = read_carmen(tmp_path / "c.log", max_range=max_range)
    else:
        with pytest.warns(NoReturnValueWarning, match=said):
            log = read_carmen(tmp_path / "c.log", max_range=max_range)
    readings = 1 + np.arange(180) / 100
    readings[5] = 81.83
    assert log.sensor["max_range_m"] == max_range
    np.testing.assert_array_equal(log.hit[:, :, 0], np.broadcast_to(readings < max_range - 0.015, (3, 180)))


def test_an_unreadable_file_or_a_folder_says_what_to_do(tmp_path, monkeypatch):
    """Not the CLI's generic 'permission denied; choose a folder you may write to': the log is read, not written."""
    path = tmp_path / "locked.log"
    path.write_text(carmen_text())
    read_bytes = Path.read_bytes

    def denied(self):
        if self == path:
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", denied)
    with pytest.raises(LogFormatError, match=r"locked.log: cannot read the log \(permission denied\); make it"):
        read_carmen(path)
    with pytest.raises(LogFormatError, match="is a folder; give the CARMEN log file in it"):
        read_carmen(tmp_path)


@pytest.mark.parametrize(
    "column, value, message",
    [
        (4, "nan", "line 4: FLASER range 4 is nan; .* write a no-return as the scanner's no-return value"),
        (180, "inf", "line 4: FLASER pose x is inf; .* repair or delete the line"),
        (182, "nan", "line 4: FLASER pose theta is nan"),
        (184, "-inf", "line 4: FLASER odometry y is -inf"),
        (186, "nan", "line 4: FLASER timestamp is nan"),
        (7, "1e39", r"line 4: FLASER range 7 is 1e\+39; ranges are finite numbers of metres below 1e\+08 m"),
        # beyond the limits every log is held to (read_any refused them as 'ray [0, 7, 0] has range of a hit 1e+09 m',
        # 1e20 after numpy's 'RuntimeWarning: invalid value encountered in cast' from the no-return detector, a
        # timestamp in ns after a TimeOrderWarning that it lies 1.7e18 s after the previous one)
        (7, "1e9", r"line 4: FLASER range 7 is 1e\+09; .* below 1e\+08 m \(a larger one is a misread number\): write"),
        (7, "1e20", r"line 4: FLASER range 7 is 1e\+20; ranges are finite numbers of metres below 1e\+08 m"),
        (
            186,
            "1.7e18",
            r"line 4: FLASER timestamp is 1.7e\+18; timestamps are finite seconds within 1e\+11 s of 1970 \(a larger "
            r"one is a misread number\): write them in seconds \(not ms, us or ns\)",
        ),
    ],
)
@pytest.mark.filterwarnings("error")  # the line is named before anything else is said about it
def test_a_non_finite_value_is_named_by_field_and_line(tmp_path, column, value, message):
    lines = carmen_text(scans=2).splitlines()
    tokens = lines[3].split()
    tokens[2 + column] = value
    lines[3] = " ".join(tokens)
    (tmp_path / "bad.log").write_text("\n".join(lines))
    with pytest.raises(LogFormatError, match=message):
        read_carmen(tmp_path / "bad.log")


@pytest.mark.parametrize(
    "name, fix",
    [
        ("RAWLASER1", "convert the laser lines to FLASER or ROBOTLASER1 lines"),  # no pose: cannot be read
        ("RLASER", "read them with --message RLASER"),  # the option, not the Python argument
        ("ROBOTLASER2", "read them with --message ROBOTLASER2"),
    ],
)
def test_other_laser_messages_are_named(tmp_path, name, fix):
    """A CARMEN log with another laser message is named as such, not asked 'is this a CARMEN log?'."""
    (tmp_path / "other.log").write_text(carmen_text(scans=2).replace("FLASER", name))
    with pytest.raises(LogFormatError, match=f"no FLASER or ROBOTLASER1 messages, but 2 {name} lines; .*: {fix}"):
        read_carmen(tmp_path / "other.log")


def test_a_message_mi_lidar_does_not_read_is_named(tmp_path):
    (tmp_path / "a.log").write_text(carmen_text(scans=2))
    with pytest.raises(ParameterError, match="message='RAWLASER1': mi-lidar reads .* FLASER, RLASER, ROBOTLASER1"):
        read_carmen(tmp_path / "a.log", message="RAWLASER1")


def test_zero_and_negative_readings_are_no_returns(tmp_path):
    """Some drivers write a no-return as 0 or a negative range: such a beam is a miss, its neighbours are not."""
    text = carmen_text(scans=2).replace(" 1.10 ", " 0.00 ", 1).replace(" 1.20 ", " -1.00 ", 1)
    (tmp_path / "z.log").write_text(text)
    log = read_carmen(tmp_path / "z.log")
    assert not log.hit[0, 10, 0] and not log.hit[0, 20, 0]
    assert log.hit[0, [9, 11, 19, 21], 0].all() and log.hit[1, [10, 20], 0].all()


def test_timestamps_that_step_back_beyond_jitter_are_warned_with_lines_and_times(tmp_path):
    """Two logs written one after the other (times restart) were read silently; benchmark-planar's leave-out maps,
    which compare timestamps (|t_j - t_q| <= 30 s), then misjudge which scans are neighbours."""
    (tmp_path / "two.log").write_text(carmen_text(scans=5, times=[100.0, 101.0, 40.0, 41.0, 0.5]))
    with pytest.warns(TimeOrderWarning) as caught:
        log = read_carmen(tmp_path / "two.log")
    (warning,) = caught
    message = str(warning.message)
    assert message.startswith(
        f"{tmp_path / 'two.log'}: line 8: FLASER timestamp 40.000 s is 61.000 s before line 6's 101.000 s "
        "(and 1 more such steps): a step back beyond clock jitter (1 s), concatenated logs?"
    ), message
    assert "benchmark-planar's leave-out maps (the scans within 1 m and 30 s of a scan" in message, message
    assert message.endswith("split the log at line 8 or make its timestamps increase"), message
    np.testing.assert_array_equal(log.times[:, 0, 0], [100.0, 101.0, 40.0, 41.0, 0.5])  # read as written


def test_small_steps_back_are_clock_jitter_and_read_silently(tmp_path):
    """The Intel log steps back four times, by up to 0.86 s: clock corrections, not a second log."""
    (tmp_path / "jitter.log").write_text(carmen_text(scans=4, times=[10.0, 11.0, 10.05, 12.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error", TimeOrderWarning)
        assert read_carmen(tmp_path / "jitter.log").times[2, 0, 0] == 10.05
        intel = read_carmen(data_file("carmen/intel-corrected.log.gz"))
    assert np.diff(intel.times[:, 0, 0]).min() == pytest.approx(-0.86, abs=1e-3)
