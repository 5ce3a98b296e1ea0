"""Planar logs that are valid but odd: the benchmark runs and says what their figures cannot show."""

import json

from tests.planar.world import room_log_text
from tests.terminal import invoke_at_80


def test_one_test_scan_has_no_reference_row_and_says_so(tmp_path):
    """A log of 3 to 5 scans has one test scan (scan 0): the reference row re-pairs beams between test scans, so every
    beam was paired with itself and the row printed a perfect sensor (|err| 0.000, F1 1.000, CRPS 0), without a word
    that the test figures rest on one scan."""
    (tmp_path / "room.log").write_text(room_log_text(scans=4))
    out = tmp_path / "out"
    args = ["benchmark-planar", tmp_path / "room.log", "--out", out, "-m", "M0", "--radius", "0", "--window", "0"]
    result = invoke_at_80(args)
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "sensor, re-paired" not in said, said
    assert (
        "warning: the log has one test scan (every 5-th scan is one), so there is no reference row (it re-pairs beams "
        "between test scans) and the test figures rest on 181 beams of one scan: give a log of 6 scans or more"
    ) in said, said
    report = json.loads((out / "benchmark.json").read_text())
    assert report["reference_repaired_sensor"] == {}
    assert any(w.startswith("the log has one test scan") for w in report["warnings"])
    assert "(reference)" not in (out / "benchmark.html").read_text()
