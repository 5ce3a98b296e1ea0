"""CARMEN logs that are valid but written in an unusual way read as their plain counterpart."""

import gzip

import numpy as np

from mi_lidar.io import read_carmen

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
