"""A CARMEN log that repeats a scan exactly (a line written twice, a stalled driver) reads each scan once."""

import numpy as np
import pytest

from mi_lidar.core.errors import DuplicateScanWarning
from mi_lidar.io import read_carmen

from .synth import carmen_text
from .test_carmen_robotlaser import drive, flaser_lines, robot_laser_lines, write


def write_text(path, text: str):
    """``path``, holding ``text``."""
    path.write_text(text)
    return path


def with_copy(text: str, line: int, stamp: float | None = None) -> str:
    """``text`` with its ``line`` (1-based) written again right after it, at timestamp ``stamp`` (None: the same)."""
    lines = text.splitlines()
    tokens = lines[line - 1].split()
    if stamp is not None:
        tokens[-3], tokens[-1] = f"{stamp}", f"{stamp}"
    return "\n".join(lines[:line] + [" ".join(tokens)] + lines[line:]) + "\n"


def test_a_line_written_twice_is_read_once_and_said(tmp_path):
    plain = read_carmen(write_text(tmp_path / "plain.log", carmen_text(scans=6)))
    with pytest.warns(DuplicateScanWarning) as said:
        log = read_carmen(write_text(tmp_path / "twice.log", with_copy(carmen_text(scans=6), line=8)))
    assert len(said) == 1
    assert log.shape == plain.shape == (6, 180, 1)
    np.testing.assert_array_equal(log.ranges, plain.ranges)
    np.testing.assert_array_equal(log.poses, plain.poses)
    np.testing.assert_array_equal(log.times, plain.times)
    message = " ".join(str(said[0].message).split())
    assert "twice.log: line 9: FLASER scan repeats line 8's exactly (the same 179 returns at the same pose" in message
    assert "dropped 1 such repeated scan of 7" in message
    assert "Nothing to do: the copies were dropped; de-duplicate the log to silence this warning" in message


def test_a_stalled_driver_repeating_its_scan_at_new_times_is_read_once(tmp_path):
    text = with_copy(with_copy(carmen_text(scans=5), line=6, stamp=11.4), line=6, stamp=11.2)  # scan 1, twice more
    with pytest.warns(DuplicateScanWarning) as said:
        log = read_carmen(write_text(tmp_path / "stalled.log", text))
    assert log.shape == (5, 180, 1)
    np.testing.assert_array_equal(log.times[:, 0, 0], [10.0, 11.0, 12.0, 13.0, 14.0])
    assert len(said) == 1
    assert "line 7: FLASER scan repeats line 6's exactly" in str(said[0].message)
    assert "dropped 2 such repeated scans of 7" in str(said[0].message)


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("returns", [0, 1, 9])
def test_repeated_scans_of_few_returns_are_kept(tmp_path, returns):
    """An open field gives the same scan of (almost) no returns from one moment to the next: not a copy."""
    ranges, robot, laser, stamps = drive(scans=6, n=180, code=81.83)
    ranges[2:5] = 81.83
    ranges[2:5, :returns] = 3.0
    laser[2:5], robot[2:5] = laser[2], robot[2]
    log = read_carmen(write(tmp_path / "field.log", flaser_lines(ranges, laser, robot, stamps)))
    assert log.shape == (6, 180, 1)
    assert log.hit[2:5].sum(axis=(1, 2)).tolist() == [returns] * 3


def test_a_repeated_scan_of_ten_returns_is_a_copy(tmp_path):
    ranges, robot, laser, stamps = drive(scans=6, n=180, code=81.83)
    ranges[2:5] = 81.83
    ranges[2:5, :10] = 3.0
    laser[2:5], robot[2:5] = laser[2], robot[2]
    with pytest.warns(DuplicateScanWarning, match="dropped 2 such repeated scans of 6"):
        log = read_carmen(write(tmp_path / "copies.log", flaser_lines(ranges, laser, robot, stamps)))
    assert log.shape == (4, 180, 1)


@pytest.mark.filterwarnings("error")
def test_a_log_without_copies_reads_silently(tmp_path):
    """The same readings at another pose, or the same pose with other readings, are other scans."""
    ranges, robot, laser, stamps = drive(scans=6, n=180, code=81.83)
    ranges[1] = ranges[0]  # the same readings, another pose
    laser[3] = laser[2]  # the same pose, other readings
    assert read_carmen(write(tmp_path / "moving.log", flaser_lines(ranges, laser, robot, stamps))).shape == (6, 180, 1)
    assert read_carmen(write_text(tmp_path / "synth.log", carmen_text(scans=5))).shape == (5, 180, 1)


def test_robot_laser_copies_are_dropped_with_their_remissions_and_robot_poses(tmp_path):
    ranges, robot, laser, stamps = drive(scans=4, n=30, code=81.83)
    remissions = np.arange(4 * 30, dtype=float).reshape(4, 30)
    lines = robot_laser_lines(ranges, laser, robot, stamps, -np.pi / 4, np.pi / 60, remissions)
    with pytest.warns(DuplicateScanWarning, match="line 4: ROBOTLASER1 scan repeats line 3's exactly"):
        log = read_carmen(write(tmp_path / "robot.clf", lines[:2] + [lines[1]] + lines[2:]))
    assert log.shape == (4, 30, 1)
    np.testing.assert_array_equal(log.attributes["intensity"][:, :, 0], remissions.astype(np.float32))
    np.testing.assert_allclose(log.sensor["robot_pose"], robot)
    np.testing.assert_allclose(log.times[:, 0, 0], stamps)
