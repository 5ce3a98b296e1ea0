"""Planar logs the benchmark cannot score get a clear error that names the value and the fix."""

import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar.protocol import PlanarProtocol, prepare
from tests.planar.world import room_log_text


def room(tmp_path, scans: int, **options):
    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=scans, **options))
    return read_carmen(path)


def test_a_one_scan_log_has_no_training_scans(tmp_path):
    """It failed with numpy's 'need at least one array to concatenate'."""
    with pytest.raises(
        LogFormatError, match=r"the log has 1 scan; .* \(every 5-th scan is a test scan\): give a longer"
    ):
        prepare(room(tmp_path, 1))


def test_a_log_too_short_to_leave_scans_out_says_so(tmp_path):
    """Five scans 0.2 s apart, all within the radius: every scan is in every map's leave-out set, so every map was
    empty and every test beam a nominal miss; the benchmark scored these empty maps without a word."""
    with pytest.raises(
        LogFormatError, match=r"no test beam of the log's 5 scans meets a wall .* 20 m and 30 s .* --window"
    ):
        prepare(room(tmp_path, 5), PlanarProtocol(radius=20.0))
