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


def test_a_moving_scanner_logged_at_one_pose_is_refused_as_fit_scene_refuses_it(tmp_path):
    """A log whose laser pose fields hold one pose while the scanner moved (Intel's scans with the first scan's pose):
    fit-scene refused it, but benchmark-planar scored leave-out maps that smear every scan together, warning only
    that the poses might not be SLAM-corrected (test returns a median 4.3 m from their maps' walls)."""
    lines = room_log_text(scans=10).splitlines()[1:]
    still = [" ".join(t[:183] + ["1", "2", "0.5"] + t[186:]) for t in (line.split() for line in lines)]
    (tmp_path / "one_pose.log").write_text("\n".join(still) + "\n")
    out = tmp_path / "out"
    result = invoke_at_80(["benchmark-planar", tmp_path / "one_pose.log", "--out", out, "-m", "M0", "--window", "0"])
    assert result.exit_code == 2, result.output
    said = " ".join(result.output.split())
    assert (
        "one_pose.log: all 10 scans have the same pose (one pose), yet a beam's returns differ between scans by a "
        "median 0.72 m: the scanner moved and the log has no poses, so the map would be a smear of every scan. Give a "
        "log with SLAM-corrected poses"
    ) in said, said
    assert not out.exists()


def test_test_scans_without_a_return_say_so_and_plot_without_a_warning(tmp_path):
    """A log whose test scans hold only the no-return value (a scanner blinded, or the value read wrong) ran, but its
    range figures were NaN without a word, and the residual plot raised numpy's 0/0 RuntimeWarning. Where such a scan
    is all its map leaves out (here --window 0, the scans over 1 m apart), it leaves out no count at all, and the
    leave-out counts indexed an empty array of corrections (IndexError)."""
    import warnings

    import numpy as np

    from mi_lidar.io.carmen import read_carmen
    from mi_lidar.planar.benchmark import run_planar_benchmark
    from mi_lidar.planar.protocol import PlanarProtocol
    from mi_lidar.planar.report import write_benchmark
    from tests.planar.world import flaser_text, poses, room_readings

    readings = room_readings(12, 181, 0.02, 0.3, 50.0, 0)
    readings[::5] = 50.0  # the test scans 0, 5 and 10: every beam a no-return
    (tmp_path / "room.log").write_text(flaser_text(poses(12), readings, "blind test scans"))
    result = run_planar_benchmark(
        read_carmen(tmp_path / "room.log"), protocol=PlanarProtocol(window=0.0), models=("M0",)
    )
    assert not result.data.test.hit.any() and np.isnan(result.rows[0].samples["histogram_l1"])
    assert any(w.startswith("no test beam returned") for w in result.warnings()), result.warnings()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        write_benchmark(result, tmp_path / "out")
    assert (tmp_path / "out" / "residuals.png").stat().st_size > 0
