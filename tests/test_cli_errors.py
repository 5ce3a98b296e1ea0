"""Every bad input of the command line is one line `error: ...` naming the value and the fix, exit code 2.

The command runs in a subprocess as a user runs it (the variant is chosen when `mi_lidar` is
imported, before the command's own error handler exists).
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mi_lidar

from .conftest import SCENES

MI_LIDAR = str(Path(sys.executable).with_name("mi-lidar"))
ROOM = str(SCENES / "indoor_planar.xml")


@pytest.fixture(scope="module")
def room_log(tmp_path_factory) -> str:
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[:, 2, 3] = 0.5
    scene = mi_lidar.load_scene(ROOM)
    return str(mi_lidar.simulate(scene, poses=poses, seed=1).save(tmp_path_factory.mktemp("room") / "room.npz"))


def read_only_folder(tmp_path: Path) -> str:
    """A folder nobody may write to: a chmod 555 folder, or (root ignores modes) one under /sys."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    return str(folder / "out") if not os.access(folder, os.W_OK) else "/sys/mi-lidar-out"


CASES = {
    "negative seed": (["render", ROOM, "--seed", "-1", "--out", "{tmp}/o"], {}, ["--seed", "'-1'", "--help"]),
    "negative scan": (["convert", "{log}", "{tmp}/x.pcd", "--scan", "-1"], {}, ["--scan", "'-1'"]),
    "scan past the end": (["convert", "{log}", "{tmp}/x.pcd", "--scan", "7"], {}, ["scan 7 out of range", "2 scans"]),
    "unknown candidate": (
        ["diagnose", "{log}", ROOM, "--out", "{tmp}/d", "--candidate", "no_such_effect"],
        {},
        ["'no_such_effect'", "outliers"],
    ),
    "narrow synthetic world": (["synth-world", "--out", "{tmp}/w.npz", "--width", "5"], {}, ["--width", "'5'", "20"]),
    "read-only output folder": (["render", ROOM, "--out", "{read_only}"], {}, ["{read_only}", "folder"]),
    "output folder is a file": (  # was '[Errno 17] File exists: ...'
        ["render", ROOM, "--out", "{file}"],
        {},
        ["{file}: file exists; a file of that name is in the way of the folder: give another path"],
    ),
    "unknown variant": (["render", ROOM, "--out", "{tmp}/o"], {"MI_LIDAR_VARIANT": "llvm_nope"}, ["'llvm_nope'"]),
    "cuda without a GPU": (
        ["render", ROOM, "--out", "{tmp}/o"],
        {"MI_LIDAR_VARIANT": "cuda_ad_rgb"},
        ["NVIDIA GPU", "llvm_ad_rgb"],
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_with_exit_code_2(tmp_path, room_log, case):
    args, env, expected = CASES[case]
    values = {"tmp": str(tmp_path), "log": room_log, "read_only": read_only_folder(tmp_path)}
    values["file"] = str(tmp_path / "a_file")
    Path(values["file"]).write_text("not a folder")
    if case == "cuda without a GPU" and os.path.exists("/dev/nvidia0"):
        pytest.skip("this machine has a GPU")
    run = subprocess.run(
        [MI_LIDAR, *(a.format(**values) for a in args)],
        capture_output=True,
        text=True,
        env={**os.environ, **env, "COLUMNS": "400"},
    )
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip()]
    assert run.returncode == 2, lines
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    for text in expected:
        assert text.format(**values) in lines[0], lines[0]


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
