"""A CARMEN log whose end was cut short (a logger stopped mid-write, a partial copy) reads up to its last complete
scan, with a TruncatedLogWarning that names the line; a short line anywhere else is still refused."""

import gzip
import warnings

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError, TruncatedLogWarning
from mi_lidar.io import read_carmen

from ..terminal import invoke_at_80
from .synth import carmen_text
from .test_carmen_robotlaser import small_log, write


def cut_last_line(text: str, keep: int) -> str:
    """``text`` with its last line cut to its first ``keep`` characters and no final newline."""
    lines = text.rstrip("\n").split("\n")
    return "\n".join(lines[:-1] + [lines[-1][:keep]])


@pytest.mark.parametrize("keep", [6, 9, 300])  # after the name, inside the beam count, inside the ranges
def test_a_last_flaser_line_cut_short_is_skipped_with_a_warning(tmp_path, keep):
    whole = read_carmen(write_text(tmp_path / "whole.log", carmen_text(scans=4)))
    path = write_text(tmp_path / "cut.log", cut_last_line(carmen_text(scans=4), keep))
    said = r"cut.log: line 10, the last, is a FLASER line cut short .* read the 3 complete scans"
    with pytest.warns(TruncatedLogWarning, match=said):
        log = read_carmen(path)
    assert log.shape == (3, 180, 1)
    np.testing.assert_array_equal(log.ranges, whole.ranges[:3])
    np.testing.assert_array_equal(log.poses, whole.poses[:3])


def test_a_short_line_before_the_end_is_still_refused(tmp_path):
    lines = carmen_text(scans=4).rstrip("\n").split("\n")
    lines[5] = lines[5][:300]  # the second scan, with more lines after it
    with pytest.raises(LogFormatError, match=r"cut.log: line 6: FLASER with n=180 needs 190 fields .*truncated"):
        read_carmen(write_text(tmp_path / "cut.log", "\n".join(lines) + "\n"))
    lines = carmen_text(scans=4).rstrip("\n").split("\n")
    lines[-1] = lines[-1].replace("FLASER 180 1.00", "FLASER 180 x")  # complete but corrupt: not a cut
    with pytest.raises(LogFormatError, match="line 10: malformed FLASER message"):
        read_carmen(write_text(tmp_path / "bad.log", "\n".join(lines)))


def test_a_last_robot_laser_line_cut_short_is_skipped_with_a_warning(tmp_path):
    lines = [" ".join(line) for line in small_log()]
    whole = read_carmen(write(tmp_path / "whole.log", lines))
    lines[-1] = lines[-1][: len(lines[-1]) // 2]
    with pytest.warns(TruncatedLogWarning, match="the last, is a ROBOTLASER1 line cut short"):
        log = read_carmen(write(tmp_path / "cut.log", lines))
    assert len(log.ranges) == len(whole.ranges) - 1
    np.testing.assert_array_equal(log.ranges, whole.ranges[:-1])


def test_a_gzip_stream_cut_short_reads_its_complete_scans(tmp_path):
    text = carmen_text(scans=40)
    packed = gzip.compress(text.encode(), compresslevel=1)
    path = tmp_path / "cut.log.gz"
    path.write_bytes(packed[: len(packed) * 2 // 3])
    with pytest.warns(TruncatedLogWarning) as caught:
        log = read_carmen(path)
    said = " ".join(str(w.message) for w in caught)
    assert "cut.log.gz: the gzip stream ends early, after" in said and "reading the complete lines" in said
    whole = read_carmen(write_text(tmp_path / "whole.log", text))
    assert 0 < len(log.ranges) < 40
    np.testing.assert_array_equal(log.ranges, whole.ranges[: len(log.ranges)])
    path.write_bytes(packed[:8])  # the header only
    with pytest.raises(LogFormatError, match="truncated gzip stream: it ends before any text; copy the log again"):
        read_carmen(path)
    path.write_bytes(packed + packed)  # two whole members (as `cat a.gz b.gz` makes) read as one text
    with warnings.catch_warnings():
        warnings.simplefilter("error", TruncatedLogWarning)
        assert len(read_carmen(path).ranges) == 80


def test_the_cli_prints_the_warning_and_reads_the_log(tmp_path):
    path = write_text(tmp_path / "cut.log", cut_last_line(carmen_text(scans=4), 300))
    result = invoke_at_80(["info", path])
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "warning: " in said and "is a FLASER line cut short" in said and "3 x 180 x 1" in said


def write_text(path, text: str):
    path.write_text(text)
    return path
