"""CARMEN logs that are valid but written in an unusual way read as their plain counterpart."""

import gzip

import numpy as np
import pytest

from mi_lidar.core.errors import BeamAnglesWarning
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


@pytest.mark.parametrize("beams", [541, 720])
def test_a_flaser_beam_count_whose_angles_are_a_guess_is_warned(tmp_path, beams):
    """FLASER lines give no field of view: 541 beams (a 270-degree scanner, 0.5 deg apart) were read over 180 degrees
    without a word, and the benchmark then blamed the poses for the walls it could not place."""
    (tmp_path / "wide.log").write_text(carmen_text(scans=2, beams=beams))
    step = 180 / (beams - 1 if beams % 2 else beams)
    with pytest.warns(BeamAnglesWarning) as said:
        log = read_carmen(tmp_path / "wide.log")
    assert log.shape == (2, beams, 1)
    assert (
        f"line 4: FLASER scans of {beams} beams; a FLASER line gives no field of view, and mi-lidar knows the beam "
        f"angles of 180, 181, 360, 361 beams (180 degrees), so these are read over 180 degrees from -90, a beam every "
        f"{step:.4g} deg. A scanner that covers another angle (541 or 1081 beams: usually 270 degrees) is read wrong: "
        "write its scans as ROBOTLASER1 lines"
    ) in str(said[0].message)


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("beams", [180, 181, 360, 361])
def test_the_sick_beam_counts_read_silently(tmp_path, beams):
    (tmp_path / "sick.log").write_text(carmen_text(scans=2, beams=beams))
    assert read_carmen(tmp_path / "sick.log").shape == (2, beams, 1)
