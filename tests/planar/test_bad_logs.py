"""Planar logs the benchmark cannot score get a clear error that names the value and the fix."""

import json

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError, ParameterError
from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar.protocol import PlanarProtocol, prepare
from tests.planar.world import flaser_text, poses, room_log_text, room_readings


def room(tmp_path, scans: int, **options):
    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=scans, **options))
    return read_carmen(path)


@pytest.mark.parametrize("scans", [1, 2])
def test_a_log_of_fewer_than_two_training_scans_is_refused(tmp_path, scans):
    """One scan failed with numpy's 'need at least one array to concatenate'. Two scans (--radius 0 --window 0, the
    first two scans of Intel) have one training scan, odd: mi-lidar's fit, which chooses its evidence classes on the
    even training scans, died with a traceback after the other models were fitted ('drjit.select ... operands have
    incompatible sizes! (sizes: 0, 0, 1)'), and NP-Reg chose its bandwidths on no beam at all."""
    s = "s" if scans > 1 else ""
    match = (
        rf"the log has {scans} scan{s}; the benchmark needs a test scan and two training scans or more \(every 5-th "
        r"scan is a test scan; the learned models choose their settings on the even training scans and check them on "
        r"the odd ones\): give a longer log"
    )
    with pytest.raises(LogFormatError, match=match):
        prepare(room(tmp_path, scans), PlanarProtocol(radius=0.0, window=0.0))


@pytest.mark.parametrize("test_every", [1, 2, 2**64])
def test_a_test_scan_spacing_outside_3_to_a_billion_is_refused(test_every):
    """2**64 (benchmark-planar or evaluate-apps --test-every) failed in numpy's modulo: 'OverflowError: Python int
    too large to convert to C long' as a traceback. 2 made every training scan odd: mi-lidar's fit died with a
    traceback ('operands have incompatible sizes! (sizes: 0, 0, 1)') after 30 s on a 60-scan log, and P-Reg and NP-Reg
    chose their bandwidths on no beam."""
    with pytest.raises(ParameterError, match=rf"test_every={test_every} must be from 3 \(training .* to 1,000,000,000"):
        PlanarProtocol(test_every=test_every)


def test_a_log_too_short_to_leave_scans_out_says_so(tmp_path):
    """Five scans 0.2 s apart, all within the radius: every scan is in every map's leave-out set, so every map was
    empty and every test beam a nominal miss; the benchmark scored these empty maps without a word."""
    with pytest.raises(
        LogFormatError, match=r"no test beam of the log's 5 scans meets a wall .* 20 m and 30 s .* --window"
    ):
        prepare(room(tmp_path, 5), PlanarProtocol(radius=20.0))


def test_empty_maps_say_where_and_when_the_scans_lie(tmp_path):
    """The advice for maps left empty was the same whatever the log: 'give a longer log that passes the same places
    more than 30 s apart, or a smaller radius or window'; for a log whose laser poses are 0 0 0 in every scan (the pose
    fields not filled) a smaller radius would have scored a map of every scan drawn at one spot: such a log is now
    refused before the map, as fit-scene refuses it (tests/planar/test_odd_logs.py), and a scanner that stood still
    gets the advice on time and place."""
    xy = poses(5)[:, :2]
    dx, dy = np.ptp(xy, axis=0)
    with pytest.raises(
        LogFormatError,
        match=rf"within 20 m and 30 s of it\), and the log's scans lie in a {dx:.2f} x {dy:.2f} m box over 0.8 s: give "
        r"a longer log that passes the same places more than 30 s apart, or a smaller radius or window",
    ):
        prepare(room(tmp_path, 5), PlanarProtocol(radius=20.0))
    still = room_readings(1, 181, 0.02, 0.3, 50.0, 0).repeat(10, axis=0)  # the range noise differs scan to scan:
    still += np.where(still < 50.0, np.random.default_rng(1).normal(0.0, 0.02, still.shape), 0.0)  # not a copy
    (tmp_path / "still.log").write_text(flaser_text(poses(1).repeat(10, axis=0), still, "a scanner standing still"))
    with pytest.raises(
        LogFormatError,
        match=r"meets a wall in its map .*, and the log's scans lie in a 0.00 x 0.00 m box over 1.8 s: give a longer "
        r"log that passes the same places more than 30 s apart, or a smaller radius or window",
    ):
        prepare(read_carmen(tmp_path / "still.log"))


@pytest.mark.parametrize("reading, no_return", [("50.000", " and from the no-return value 50 m up"), ("0.000", "")])
def test_a_log_without_returns_has_no_map(tmp_path, reading, no_return):
    """Every beam a no-return (the code, or 0): it failed with numpy's 'index -1 is out of bounds for axis 0'."""
    text = room_log_text(scans=10, beams=5)
    lines = [" ".join(t[:2] + [reading] * 5 + t[7:]) for t in (line.split() for line in text.splitlines()[1:])]
    (tmp_path / "misses.log").write_text("\n".join(lines) + "\n")
    log = read_carmen(tmp_path / "misses.log", max_range=50.0 if no_return else None)
    match = rf"none of the log's 50 readings is a return closer than 40 m \(readings <= 0{no_return} are no-returns\)"
    with pytest.raises(LogFormatError, match=match + ".* check the no-return value"):
        prepare(log)


def test_a_far_off_pose_is_named_before_the_map_is_allocated(tmp_path):
    """A pose at x = 1e9 m: it failed with 'MemoryError: Unable to allocate 89.2 TiB' from the count map."""
    lines = room_log_text(scans=10, beams=5).splitlines()
    tokens = lines[4].split()
    tokens[7] = "1e6"  # the corrected pose x of the 4th scan
    lines[4] = " ".join(tokens)
    (tmp_path / "far.log").write_text("\n".join(lines) + "\n")
    match = r"the map would span 1,000,0\d\d x \d+ m .* scan 4 of 10 is at x=1e\+06, .* check the log's poses"
    with pytest.raises(LogFormatError, match=match):
        prepare(read_carmen(tmp_path / "far.log"))


def test_an_out_path_that_is_a_file_fails_before_the_run(tmp_path, monkeypatch):
    """It failed only after the whole run (minutes on a real log), when the report was written."""
    import mi_lidar.planar.benchmark as benchmark
    from tests.terminal import invoke_at_80

    def must_not_run(*args, **kwargs):
        raise AssertionError("the benchmark ran although its report folder cannot be made")

    monkeypatch.setattr(benchmark, "run_planar_benchmark", must_not_run)
    (tmp_path / "room.log").write_text(room_log_text(scans=10))
    (tmp_path / "report").write_text("in the way")
    result = invoke_at_80(["benchmark-planar", tmp_path / "room.log", "--out", tmp_path / "report"])
    assert result.exit_code == 2, result.output
    assert "file exists" in result.output and "in the way of the folder" in result.output, result.output


def test_a_map_too_sparse_for_the_log_is_named(tmp_path):
    """Leave-out sets of 5 m and 5 s around scans 0.2 s apart leave half the test beams' walls out of their maps
    (measured: 54 % of the test beams returned where their map has no wall); the figures were printed unremarked."""
    from tests.terminal import invoke_at_80

    (tmp_path / "room.log").write_text(room_log_text(scans=30))
    args = ["benchmark-planar", tmp_path / "room.log", "--out", tmp_path / "out", "-m", "M0"]
    result = invoke_at_80([*args, "--radius", "5", "--window", "5"])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "out" / "benchmark.json").read_text())
    unmapped = report["nominal"]["unmapped_returns"]
    assert unmapped > 0.4
    assert f"warning: {unmapped:.0%} of the test beams returned where their leave-out map has no wall" in " ".join(
        result.output.split()
    )


def drifted(text: str, step: tuple[float, float, float], seed: int = 0) -> str:
    """``text`` (CARMEN) with its poses drifting like odometry: a random walk of ``step`` (m, m, rad) per scan."""
    lines = text.splitlines()
    drift = np.cumsum(np.random.default_rng(seed).normal(0.0, step, (len(lines) - 1, 3)), axis=0)
    out = [lines[0]]
    for line, d in zip(lines[1:], drift):
        t = line.split()
        at = 2 + int(t[1])
        pose = [f"{float(v) + e:.5f}" for v, e in zip(t[at : at + 3], d)]
        t[at : at + 3], t[at + 3 : at + 6] = pose, pose
        out.append(" ".join(t))
    return "\n".join(out) + "\n"


def test_poses_that_drift_are_named(tmp_path):
    """Readings taken at the true poses, logged with poses drifting 5 cm and 0.6 deg per scan (odometry): the
    benchmark scored the blurred maps without a word (Intel with its odometry's poses: M0 and M3b about 2
    nats worse, no warning). Measured: test returns a median 0.21 m from their maps' walls, 0.06 m with the
    true poses, which get no warning."""
    from tests.terminal import invoke_at_80

    for name, text in (
        ("true", room_log_text(scans=60)),
        ("drift", drifted(room_log_text(scans=60), (0.05, 0.05, 0.01))),
    ):
        (tmp_path / f"{name}.log").write_text(text)
        args = ["benchmark-planar", tmp_path / f"{name}.log", "--out", tmp_path / name, "-m", "M0", "--window", "1"]
        result = invoke_at_80(args)
        assert result.exit_code == 0, result.output
        off = json.loads((tmp_path / name / "benchmark.json").read_text())["nominal"]["median_abs_err"]
        warned = "warning: the test returns lie a median" in " ".join(result.output.split())
        assert warned == (name == "drift"), (name, off, result.output)
        assert (off > 0.15) == (name == "drift"), (name, off)
        report = json.loads((tmp_path / name / "benchmark.json").read_text())
        html = (tmp_path / name / "benchmark.html").read_text()
        assert (len(report["warnings"]) == 1) == (name == "drift") == ("<b>Warning:</b> the test returns lie" in html)


def test_a_report_that_fails_while_written_leaves_the_previous_one_whole(tmp_path, monkeypatch):
    """A run stopped while writing left a new benchmark.json beside the old benchmark.html (the input audit)."""
    import mi_lidar.planar.report as report
    from mi_lidar.planar.benchmark import run_planar_benchmark

    result = run_planar_benchmark(room(tmp_path, 30), models=("M0",), protocol=PlanarProtocol(window=5.0))
    out = tmp_path / "report"
    report.write_benchmark(result, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert set(before) == {"benchmark.json", "benchmark.html", "nll.png", "residuals.png", "nll_by_range.png"}

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "range_figure", stopped)  # after the JSON and two figures are written
    (out / "benchmark.json").write_bytes(b"{}")  # the old report, as another run left it
    before["benchmark.json"] = b"{}"
    with pytest.raises(KeyboardInterrupt):
        report.write_benchmark(result, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing new moved in, no staging left
    monkeypatch.undo()
    files = report.write_benchmark(result, out)
    assert json.loads((out / "benchmark.json").read_text())["models"][0]["model"] == "M0"
    assert all(path.parent == out and path.exists() for path in files.values())
    assert sorted(p.name for p in out.iterdir()) == sorted(before)


def test_a_report_write_that_fails_names_the_file_in_the_report_folder(tmp_path, monkeypatch):
    """Under `ulimit -f` benchmark-planar said 'error: .../report/.benchmark-ndc82j3f/nll_by_range.png: file too
    large; ...': a file of its staging folder, removed before the message was read."""
    import errno

    import mi_lidar.planar.report as report
    from mi_lidar.planar.benchmark import run_planar_benchmark

    result = run_planar_benchmark(room(tmp_path, 30), models=("M0",), protocol=PlanarProtocol(window=5.0))

    def too_large(result, path):
        raise OSError(errno.EFBIG, "File too large", str(path))  # as atomic_path names a failed write

    monkeypatch.setattr(report, "range_figure", too_large)
    with pytest.raises(OSError) as error:
        report.write_benchmark(result, tmp_path / "report")
    assert error.value.filename == str(tmp_path / "report" / "nll_by_range.png")
    assert list((tmp_path / "report").iterdir()) == []


@pytest.mark.parametrize("verb", ["benchmark-planar", "evaluate-apps"])
def test_a_point_cloud_is_named_as_one(tmp_path, verb):
    """A PLY point cloud was read as CARMEN text: 'scan.ply: no FLASER messages; is this a CARMEN log?'."""
    from mi_lidar.io.dispatch import write_any
    from tests.io.test_clouds import synthetic_log
    from tests.terminal import invoke_at_80

    path = write_any(synthetic_log(), tmp_path / "scan.ply")
    result = invoke_at_80([verb, path, "--out", tmp_path / "out"])
    assert result.exit_code == 2, result.output
    said = " ".join(result.output.split())
    assert "scan.ply: a PLY point cloud (.ply) by its extension; expected a CARMEN log (.log, .log.gz, .clf)" in said
    assert "give the file in that format (for a log converted from one, the original)" in said  # there was no fix


@pytest.mark.parametrize("name", ["room.txt", "room.gz", "room"])
def test_a_carmen_log_under_any_other_name_is_read_as_one(tmp_path, name):
    """Real CARMEN logs travel as .log, .gfs.log, .clf, .txt or bare names: benchmark-planar and evaluate-apps read
    the one format they take whatever the name (5b77732 refused every name but .log, .log.gz, .clf), and still
    refuse a file that names another format."""
    import gzip

    from mi_lidar.io.dispatch import read_any

    text = room_log_text(scans=6)
    path = tmp_path / name
    path.write_bytes(gzip.compress(text.encode()) if name.endswith(".gz") else text.encode())
    log = read_any(path, formats=("carmen",))
    assert log.ranges.shape[0] == 6
    np.testing.assert_array_equal(log.ranges, room(tmp_path, 6).ranges)
    (tmp_path / "scan.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(LogFormatError, match="PLY point cloud"):
        read_any(tmp_path / "scan.ply", formats=("carmen",))


@pytest.mark.parametrize("verb", ["benchmark-planar", "evaluate-apps"])
def test_message_picks_the_laser_lines_and_names_what_the_log_has(tmp_path, verb):
    """``--message`` reaches the reader: a log of FLASER lines read as RLASER is refused with what it holds and the
    option that reads it; an unknown name is refused with the names mi-lidar reads."""
    from tests.terminal import invoke_at_80

    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=6))
    for name, expected in (
        ("RLASER", "no RLASER messages, but 6 FLASER lines"),
        ("RLASER", "read them with --message FLASER"),  # was message='FLASER', a Python argument
        ("LASER", "message='LASER': mi-lidar reads the laser messages with a pose"),
    ):
        result = invoke_at_80([verb, path, "--out", tmp_path / "out", "--message", name])
        assert result.exit_code == 2, result.output
        assert expected in " ".join(result.output.split()), result.output
