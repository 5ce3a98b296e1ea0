"""Every bad input of the command line is one line `error: ...` naming the value and the fix, exit code 2.

The command runs in a subprocess as a user runs it (the variant is chosen when `mi_lidar` is
imported, before the command's own error handler exists).
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mi_lidar

from .conftest import REPO, SCENES
from .planar.world import room_log_text

MI_LIDAR = str(Path(sys.executable).with_name("mi-lidar"))
ROOM = str(SCENES / "indoor_planar.xml")
HUGE = "1000000000000"  # a count of 10**12: a typo that would allocate terabytes or run for years
PROGRESS = re.compile(r".+: (\d+/\d+|done) \(\d+ s\)$")  # the plain progress lines of work done before the error


@pytest.fixture(scope="module")
def room_log(tmp_path_factory) -> str:
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[:, 2, 3] = 0.5
    scene = mi_lidar.load_scene(ROOM)
    return str(mi_lidar.simulate(scene, poses=poses, seed=1).save(tmp_path_factory.mktemp("room") / "room.npz"))


@pytest.fixture(scope="module")
def street_frame(tmp_path_factory) -> str:
    """One VLP-16 scan of the urban street: a frame `evaluate-apps-3d` reads."""
    pose = np.eye(4)[None].copy()
    pose[:, 2, 3] = 1.8
    scene = mi_lidar.load_scene(SCENES / "urban_street.xml")
    return str(mi_lidar.simulate(scene, poses=pose, seed=1).save(tmp_path_factory.mktemp("street") / "frame.npz"))


@pytest.fixture(scope="module")
def carmen_log(tmp_path_factory) -> str:
    """A planar CARMEN log: 60 scans of the test room, 12 s in all."""
    path = tmp_path_factory.mktemp("carmen") / "room.log"
    path.write_text(room_log_text())
    return str(path)


def read_only_folder(tmp_path: Path) -> str:
    """A folder nobody may write to: a chmod 555 folder, or (root ignores modes) one under /sys."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    return str(folder / "out") if not os.access(folder, os.W_OK) else "/sys/mi-lidar-out"


CASES = {
    "negative seed": (["render", ROOM, "--seed", "-1", "--out", "{tmp}/o"], {}, ["--seed", "'-1'", "--help"]),
    "negative scan": (["convert", "{log}", "{tmp}/x.pcd", "--scan", "-1"], {}, ["--scan", "'-1'"]),
    "scan past the end": (
        ["convert", "{log}", "{tmp}/x.pcd", "--scan", "7"],
        {},
        ["cannot write scan 7: the log holds 2 scans", "from 0 to 1"],
    ),
    "unknown candidate": (
        ["diagnose", "{log}", ROOM, "--out", "{tmp}/d", "--candidate", "no_such_effect"],
        {},
        ["'no_such_effect'", "outliers"],
    ),
    "density parameter not a number": (  # was 'could not convert string to float: 'abc''
        ["compare", "{log}", ROOM, "--out", "{tmp}/c", "--density", "physics(k=abc)"],
        {},
        ["density 'physics': k='abc' is not a number"],
    ),
    "density list with a word": (
        ["compare", "{log}", ROOM, "--out", "{tmp}/c", "--density", "physics(k=[1 x])"],
        {},
        ["density 'physics': k=['1', 'x'] is not a number"],
    ),
    "log given as an annotation": (  # was the 'utf-8' codec's words
        ["compose", "{log}", "--library", "{tmp}", "--out", "{tmp}/x.xml"],
        {},
        ["room.npz: a binary file, not an annotation", "`mi-lidar annotate LOG.npz --out annotation.json`"],
    ),
    "annotate a log without instances": (  # the advice was a Python function
        ["annotate", "{log}", "--out", "{tmp}/a.json"],
        {},
        ["room.npz: the log has no per-ray instance", "`mi-lidar synth-world --out train.npz`"],
    ),
    "compare's arguments swapped": (  # was 'unknown extension '.xml''
        ["compare", ROOM, "{log}", "--out", "{tmp}/c"],
        {},
        ["indoor_planar.xml is a scene XML: the first argument is the log, the second the scene"],
    ),
    "diagnose's arguments swapped": (
        ["diagnose", ROOM, "{log}", "--out", "{tmp}/d"],
        {},
        ["the first argument is the log", "`mi-lidar diagnose LOG SCENE.xml ...`"],
    ),
    "fit-sensor's arguments swapped": (
        ["fit-sensor", ROOM, "{log}", "--out", "{tmp}/m.npz"],
        {},
        ["the first argument is the log", "`mi-lidar fit-sensor LOG SCENE.xml ...`"],
    ),
    "narrow synthetic world": (["synth-world", "--out", "{tmp}/w.npz", "--width", "5"], {}, ["--width", "'5'", "20"]),
    "read-only output folder": (["render", ROOM, "--out", "{read_only}"], {}, ["{read_only}", "folder"]),
    "output folder is a file": (  # was '[Errno 17] File exists: ...'
        ["render", ROOM, "--out", "{file}"],
        {},
        ["{file}: file exists; a file of that name is in the way of the folder: give another path"],
    ),
    "output file is a folder": (  # named the temporary file ('.folder.x1y2.tmp.npz: is a directory')
        ["simulate", ROOM, "--poses", "{log}", "--out", "{folder}"],
        {},
        ["error: {folder}: is a directory; the path is a folder: give a file name"],
    ),
    "repeated option": (["render", ROOM, "--seed", "1", "--seed", "-1", "--out", "{tmp}/o"], {}, ["(got '-1')"]),
    "NaN for a number in a range": (  # said 'Input should be less than or equal to 1 (got 'nan')'
        ["benchmark-planar", "{carmen}", "--out", "{tmp}/b", "--cell", "nan"],
        {},
        ["--cell", "'nan' is not a number", "0.005<=x<=1.0"],
    ),
    # numbers a typo makes huge, each refused before any work (were tracebacks, terabyte allocations or endless runs)
    "render seed beyond 32 bits": (
        ["render", ROOM, "--seed", "4294967296", "--out", "{tmp}/o"],
        {},
        ["--seed", "4294967295"],
    ),
    "demo seed beyond 32 bits": (
        ["demo", "--seed", HUGE, "--out", "{tmp}/o"],
        {},
        ["--seed", f"'{HUGE}'", "4294967295"],
    ),
    "huge image width": (
        ["camera-lidar", ROOM, "--out", "{tmp}/o", "--width", HUGE],
        {},
        ["--width", f"'{HUGE}'", "8192"],
    ),
    "huge image height": (["camera-lidar", ROOM, "--out", "{tmp}/o", "--height", HUGE], {}, ["--height", "8192"]),
    "huge samples per pixel": (["camera-lidar", ROOM, "--out", "{tmp}/o", "--spp", HUGE], {}, ["--spp", "4096"]),
    "fit-sensor steps": (
        ["fit-sensor", "{log}", ROOM, "-m", "beam", "--out", "{tmp}/s.npz", "--steps", HUGE],
        {},
        ["--steps", "100000"],
    ),
    "calibrate steps": (
        ["calibrate", "{log}", ROOM, "-p", "sensor.*", "--out", "{tmp}/c", "--steps", HUGE, "--patience", HUGE],
        {},
        ["--steps", "100000"],
    ),
    "3D draws": (["evaluate-apps-3d", "{frame}", "--out", "{tmp}/a", "--draws", HUGE], {}, ["--draws", "1000"]),
    "3D starts": (["evaluate-apps-3d", "{frame}", "--out", "{tmp}/a", "--starts", HUGE], {}, ["--starts", "100"]),
    "planar log to the 3D evaluation": (  # named neither the file nor what to give
        ["evaluate-apps-3d", "{carmen}", "--out", "{tmp}/a"],
        {},
        ["{carmen}: the frame has 1 column(s) of 181 beams; the column protocol needs 16", "not a planar scan"],
    ),
    "3D negative seed": (["evaluate-apps-3d", "{frame}", "--out", "{tmp}/a", "--seed", "-1"], {}, ["--seed", "'-1'"]),
    "planar draws": (["evaluate-apps", "{carmen}", "--out", "{tmp}/a", "--draws", HUGE], {}, ["--draws", "1000"]),
    "planar runs": (["evaluate-apps", "{carmen}", "--out", "{tmp}/a", "--runs", HUGE], {}, ["--runs", "32"]),
    "planar workers": (["evaluate-apps", "{carmen}", "--out", "{tmp}/a", "--workers", HUGE], {}, ["--workers", "3"]),
    "unreadable planar log": (  # the report folder was made before the log was read, and left empty
        ["benchmark-planar", "{file}", "--out", "{tmp}/b"],
        {},
        ["{file}"],
    ),
    "max range beyond 10 km": (
        ["benchmark-planar", "{carmen}", "--out", "{tmp}/b", "--max-range", "1e12"],
        {},
        ["--max-range", "10000"],
    ),
    "dataset workers": (
        ["dataset", str(REPO / "examples" / "datasets" / "street_quick.yaml"), "--out", "{tmp}/d", "--workers", HUGE],
        {},
        ["--workers", f"'{HUGE}'"],
    ),
    "dataset retries": (
        ["dataset", str(REPO / "examples" / "datasets" / "street_quick.yaml"), "--out", "{tmp}/d", "--retries", HUGE],
        {},
        ["--retries", "100"],
    ),
    # values refused by the library with the option's name (were NaN in the calibrated scene, or numpy's words)
    "infinite learning-rate factor": (
        ["calibrate", "{log}", ROOM, "-p", "sensor.range_bias", "--out", "{tmp}/c", "--lr-scale", "inf"],
        {},
        ["lr_scale=inf", "finite numbers > 0"],
    ),
    "negative learning-rate factor": (
        ["calibrate", "{log}", ROOM, "-p", "sensor.range_bias", "--out", "{tmp}/c", "--lr-scale", "-1"],
        {},
        ["lr_scale=-1.0", "finite numbers > 0"],
    ),
    "infinite learning rate": (
        ["calibrate", "{log}", ROOM, "-p", "sensor.range_bias", "--out", "{tmp}/c", "--lr", "sensor.*=inf"],
        {},
        ["sensor.*=inf", "learning rates"],
    ),
    "camera looking straight up": (
        ["camera-lidar", ROOM, "--out", "{tmp}/o", "--from", "0,0,1", "--to", "0,0,5"],
        {},
        ["[0.0, 0.0, 1.0]", "[0.0, 0.0, 5.0]", "move the target"],
    ),
    "no map left for the applications": (  # 60 scans in 12 s, one group: every scan is left out of its map
        [
            "evaluate-apps",
            "{carmen}",
            "--out",
            "{tmp}/a",
            "-s",
            "M0",
            "--draws",
            "2",
            "--runs",
            "1",
            "--test-every",
            "100",
        ],
        {},
        ["test_every=100", "--test-every", "--window"],
    ),
    "scene value a plugin refuses": (  # was Mitsuba's message with the plugin's Python traceback in it
        ["render", "{refused_scene}", "--out", "{tmp}/o"],
        {},
        [
            'refused.xml (line 14, col 6): failed to instantiate sensor plugin of type "lidar": lidar sensor: '
            "max_range=nan m is outside [0, 1e+08] m, or inf for no far end (a distance beyond 1e+08 m is a misread "
            "number); fix the value in the scene"
        ],
    ),
    "scene without a lidar integrator": (  # was Mitsuba's 'No integrator specified!' in a rich traceback
        ["render", "{bare_scene}", "--out", "{tmp}/o"],
        {},
        ['bare.xml: the scene\'s integrator is none, not a lidar_integrator; add <integrator type="lidar_integrator"'],
    ),
    "stray text in a scene": (  # the pane's p_hit, its '<' escaped, was dropped without a word
        ["render", "{stray_scene}", "--out", "{tmp}/o"],
        {},
        [
            """stray.xml: line 61, column 37: stray text '<float name="p_hit" value="0.3"/>' in """
            '<bsdf type="lidar_material">; a Mitsuba scene holds only elements'
        ],
    ),
    "a range window of 1e30 m": (  # was rendered
        ["render", "{far_scene}", "--out", "{tmp}/o"],
        {},
        [
            "lidar sensor: max_range=1e+30 m is outside [0, 1e+08] m, or inf for no far end (a distance beyond 1e+08 m "
            "is a misread number); fix the value in the scene"
        ],
    ),
    "a range noise of 1e30 m": (  # was rendered: a few returns, the others drawn outside the range window
        ["render", ROOM, "--out", "{tmp}/o", "--density", "physics(sigma0=1e30)"],
        {},
        ["density 'physics': sigma0=1e+30 m is outside [0, 1000]"],
    ),
    "unknown variant": (["render", ROOM, "--out", "{tmp}/o"], {"MI_LIDAR_VARIANT": "llvm_nope"}, ["'llvm_nope'"]),
    "cuda without a GPU": (
        ["render", ROOM, "--out", "{tmp}/o"],
        {"MI_LIDAR_VARIANT": "cuda_ad_rgb"},
        ["NVIDIA GPU", "llvm_ad_rgb"],
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_with_exit_code_2(tmp_path, room_log, street_frame, carmen_log, case):
    args, env, expected = CASES[case]
    values = {"tmp": str(tmp_path), "log": room_log, "frame": street_frame, "carmen": carmen_log}
    values["read_only"] = read_only_folder(tmp_path)
    values["file"] = str(tmp_path / "a_file")
    Path(values["file"]).write_text("not a folder")
    values["folder"] = str(tmp_path / "folder.npz")
    Path(values["folder"]).mkdir()
    values["refused_scene"] = str(tmp_path / "refused.xml")
    Path(values["refused_scene"]).write_text(
        Path(ROOM).read_text().replace('"max_range" value="30"', '"max_range" value="nan"')
    )
    values["far_scene"] = str(tmp_path / "far.xml")
    Path(values["far_scene"]).write_text(
        Path(ROOM).read_text().replace('"max_range" value="30"', '"max_range" value="1e30"')
    )
    values["stray_scene"] = str(tmp_path / "stray.xml")
    Path(values["stray_scene"]).write_text(
        Path(ROOM).read_text().replace('<float name="p_hit"', '&lt;float name="p_hit"')
    )
    values["bare_scene"] = str(tmp_path / "bare.xml")
    Path(values["bare_scene"]).write_text(
        re.sub(r"<integrator .*?</integrator>", "", Path(ROOM).read_text(), flags=re.S)
    )
    if case == "cuda without a GPU" and os.path.exists("/dev/nvidia0"):
        pytest.skip("this machine has a GPU")
    outs = [Path(args[i + 1].format(**values)) for i, a in enumerate(args[:-1]) if a in ("--out", "-o")]
    fresh = [out for out in outs if not out.exists()]
    run = subprocess.run(
        [MI_LIDAR, *(a.format(**values) for a in args)],
        capture_output=True,
        text=True,
        env={**os.environ, **env, "COLUMNS": "400"},
    )
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip() and not PROGRESS.match(line)]
    assert run.returncode == 2, lines
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    for text in expected:
        assert text.format(**values) in lines[0], lines[0]
    left = [str(out) for out in fresh if out.exists()]
    assert not left, f"a failed run left its output behind: {left}"


def test_an_error_is_printed_as_written_not_read_as_markup(tmp_path):
    """'[x, y]' in a message is text, not a rich style tag (it used to vanish from the line)."""
    spec = tmp_path / "spec.yaml"
    spec.write_text(
        "rig: {lidars: [{pattern: vlp16}], cameras: [{name: c}]}\n"
        f"scenes: [{{name: s, xml: {ROOM}, frames: 1, trajectory: {{waypoints: [[0, 0, 0, 1], [1, 0]]}}}}]\n"
    )
    run = subprocess.run(
        [MI_LIDAR, "dataset", str(spec), "--out", str(tmp_path / "d")],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "400"},
    )
    assert run.returncode == 2, run.stdout + run.stderr
    assert "waypoint 0 has 4 numbers; give [x, y] or [x, y, z] (m)" in run.stdout + run.stderr


def test_a_denied_read_and_a_denied_write_both_get_the_fix_for_what_was_done(tmp_path):
    """The handler cannot tell a read from a write: the line names the file and the access each one needs
    (it told a user who could not read a file to choose a folder they may write to)."""
    from mi_lidar.cli.app import os_error_line

    secret = tmp_path / "secret.txt"
    secret.write_text("x")
    secret.chmod(0)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    if os.access(secret, os.R_OK) or os.access(locked, os.W_OK):
        pytest.skip("file modes do not bind this process (root)")
    with pytest.raises(PermissionError) as read:
        secret.read_text()
    with pytest.raises(PermissionError) as write:
        (locked / "out.txt").write_text("x")
    for exc, path in ((read.value, secret), (write.value, locked / "out.txt")):
        line = os_error_line(exc)
        assert line.startswith(f"{path}: permission denied; "), line
        assert "reading a file needs read access to it, writing one needs write access to its folder" in line, line


def limited_size(limit: int):
    """A preexec_fn capping the files the command writes at ``limit`` bytes (`ulimit -f`): a write past it fails
    with EFBIG, as on a full disk (Python ignores SIGXFSZ)."""

    def apply() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    return apply


WRITES = {  # command, the output it fails to write, what was printed before
    "npz": (["convert", "{log}", "{out}"], "out.npz", "[Errno 27] File too large"),
    "exr": (["convert", "{log}", "{out}", "--scan", "0"], "out.exr", "a traceback: OpenEXR's RuntimeError"),
    "bin": (["convert", "{log}", "{out}", "--scan", "0"], "out.bin", "22408 requested and 12800 written"),
    "bag": (["convert", "{log}", "{out}"], "bag", "a traceback: sqlite3.OperationalError: disk I/O error"),
    "render": (["render", ROOM, "--out", "{out}"], "scan", "a traceback, and the empty folder left behind"),
}


@pytest.mark.parametrize("case", sorted(WRITES))
def test_a_write_that_fails_midway_names_the_file_keeps_the_old_one_and_leaves_nothing(tmp_path, room_log, case):
    args, name, before = WRITES[case]
    out = tmp_path / name
    if case not in ("bag", "render"):
        out.write_bytes(b"the previous file")
    run = subprocess.run(
        [MI_LIDAR, *(a.format(log=room_log, out=out) for a in args)],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "400"},
        preexec_fn=limited_size(1000),
    )
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip() and not PROGRESS.match(line)]
    # Dr.Jit writes each kernel it has not cached to ~/.drjit under the same limit and says so itself (a cold
    # cache, as on a fresh CI machine): that line is Dr.Jit's, not the command's
    lines = [line for line in lines if "while writing compiled kernel to cache file" not in line]
    assert run.returncode == 2 and len(lines) == 1, (before, lines)
    written = out / "scan.exr" if case == "render" else out
    assert lines[0].startswith(f"error: {written}: "), (before, lines)
    assert "ulimit -f" in lines[0], lines
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ([name] if case not in ("bag", "render") else []), left
    if case not in ("bag", "render"):
        assert out.read_bytes() == b"the previous file"


@pytest.fixture(scope="module")
def world_log(tmp_path_factory) -> str:
    """A small labeled off-road log, as `fit-scene` reads."""
    path = tmp_path_factory.mktemp("world") / "world.npz"
    args = ["synth-world", "--out", str(path), "--seed", "11", "--length", "20", "--width", "20"]
    run = subprocess.run([MI_LIDAR, *args], capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    return str(path)


SCENE_WRITES = {  # command, what a write that failed midway left before
    "calibrate": (
        ["calibrate", "{log}", ROOM, "-p", "elements.*.p_hit", "--steps", "1", "--out", "{out}"],
        "the new box_obstacle, glass_pane and partition PLYs in scene_assets/, beside no scene.xml or the previous one",
    ),
    "fit-scene": (["fit-scene", "{world}", "--out", "{out}"], "an empty scene_assets/ beside no scene.xml"),
}


@pytest.mark.parametrize("previous", [False, True], ids=["fresh", "previous output"])
@pytest.mark.parametrize("case", sorted(SCENE_WRITES))
def test_a_scene_and_its_assets_appear_together_or_not_at_all(tmp_path, room_log, world_log, case, previous):
    args, before = SCENE_WRITES[case]
    out = tmp_path / "out"
    kept = {"scene.xml": b"<scene/>", "scene_assets/old.ply": b"the previous asset"}
    for name, content in kept.items() if previous else ():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_bytes(content)
    run = subprocess.run(
        [MI_LIDAR, *(a.format(log=room_log, world=world_log, out=out) for a in args)],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "400"},
        preexec_fn=limited_size(1000),
    )
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip() and not PROGRESS.match(line)]
    lines = [line for line in lines if "while writing compiled kernel to cache file" not in line]  # Dr.Jit's
    assert run.returncode == 2 and len(lines) == 1, (before, lines)
    assert lines[0].startswith(f"error: {out / 'scene_assets'}/") and "ulimit -f" in lines[0], (before, lines)
    left = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()} if out.exists() else {}
    assert left == (kept if previous else {}), (before, sorted(left))
    assert not out.exists() or previous, (before, sorted(p.name for p in out.iterdir()))
