"""CARMEN logs that are valid but written in an unusual way read as their plain counterpart."""

import gzip

import numpy as np

from mi_lidar.io import read_carmen

from ..terminal import invoke_at_80
from .synth import carmen_text


def test_a_byte_order_mark_does_not_hide_the_first_scan(tmp_path):
    """A log saved by a Windows editor starts with a UTF-8 byte order mark: its first line read as '\\ufeffFLASER', not
    a FLASER line, and the first scan was dropped without a word (3 scans read as 2)."""
    text = "\n".join(carmen_text(scans=3).splitlines()[3:]) + "\n"  # the first line is a FLASER line
    (tmp_path / "plain.log").write_text(text)
    (tmp_path / "bom.log").write_bytes(b"\xef\xbb\xbf" + text.encode())
    (tmp_path / "bom.log.gz").write_bytes(gzip.compress(b"\xef\xbb\xbf" + text.encode()))
    plain = read_carmen(tmp_path / "plain.log")
    assert plain.shape == (3, 180, 1)
    for name in ("bom.log", "bom.log.gz"):
        np.testing.assert_array_equal(read_carmen(tmp_path / name).ranges, plain.ranges)


def test_info_shows_the_no_return_value_it_detects(tmp_path):
    """`mi-lidar info` on a CARMEN log did not say which no-return value it read the log with (a scanner clipped at
    8 m, or none), so a newcomer learned whether it was detected right only at the end of a benchmark run."""
    (tmp_path / "clipped.log").write_text(carmen_text(scans=40, max_range=8.0))  # one no-return a scan
    (tmp_path / "none.log").write_text(carmen_text(scans=3, max_range=5.0))  # 5 m: one reading a scan, a return
    said = {
        name: " ".join(invoke_at_80(["info", tmp_path / name]).output.split()) for name in ("clipped.log", "none.log")
    }
    assert "no-return value (m) │ 8.00 │" in said["clipped.log"], said
    assert "no-return value (m) │ none in the log │" in said["none.log"], said
