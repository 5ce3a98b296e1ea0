"""fit-scene says what it wrote, and warns that a planar log cannot show a hybrid scene's ground and vegetation."""

import numpy as np
import pytest
from typer.testing import CliRunner

import mi_lidar
from mi_lidar.cli import app
from mi_lidar.hybrid.commands import fit_scene

from ..conftest import SCENES
from ..io.test_clouds import synthetic_log


def test_a_planar_log_is_warned_about(tmp_path, capsys):
    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3], poses[:, 2, 3] = [0.0, 0.5, 1.0], 0.5
    log = mi_lidar.simulate(scene, poses=poses, seed=1)
    log.attributes["label"] = np.ones_like(log.hit, np.int32)  # the fit reads labels
    path = log.save(tmp_path / "room.npz")
    xml, *_ = fit_scene(path, tmp_path / "fitted", preview=False)
    said = capsys.readouterr().err
    assert xml.is_file() and f"warning: {path} is a planar log (every beam in one plane)" in said  # one line


TWO_POINTS = (
    "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
)
TWO_POINTS += "1 0 0\n0 1 1\n"


def nan_pose_log(path):
    log = synthetic_log(scans=2)
    log.poses[1, 0, 3] = np.nan
    return log.save(path)


@pytest.mark.parametrize(
    "make, said",
    [
        (nan_pose_log, "log.npz: pose 1 is not a rigid transform: has non-finite entries"),
        (lambda path: path.write_bytes(b""), "log.ply: empty file (0 bytes), not a PLY point cloud"),
        (  # was 'the scene has no shapes; add a mesh or an ellipsoid set', naming no file
            lambda path: path.write_text(TWO_POINTS),
            "log.ply: the fit found neither ground nor vegetation in the log's 2 returns; give a 3D log",
        ),
    ],
    ids=["nan-pose", "empty-ply", "two-points"],
)
def test_a_bad_log_is_one_error_line_naming_the_file(tmp_path, make, said):
    """A NaN pose said matplotlib's 'data must be finite, check for nan or inf values'; any file but a .npz was
    'not a readable mi-lidar log' (fit-scene read with Log.load, not read_any)."""
    path = tmp_path / ("log.npz" if make is nan_pose_log else "log.ply")
    make(path)
    result = CliRunner().invoke(app, ["fit-scene", str(path), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert said in " ".join(result.output.split()) and lines[0].startswith("error:"), result.output
    assert not (tmp_path / "out").exists()


def test_fit_scene_and_annotate_print_counts_with_thousands_separators(tmp_path, small_log, monkeypatch):
    """fit-scene's table and annotate's line printed '25970' points and '2607 ground triangles' where every other
    command prints 12,345."""
    import io
    import re

    from rich.console import Console

    from mi_lidar.hybrid import commands

    printed = io.StringIO()
    monkeypatch.setattr(commands, "console", Console(file=printed, width=400))
    path = small_log.save(tmp_path / "world.npz")
    fit_scene(path, tmp_path / "fitted", preview=False)
    commands.annotate(path, tmp_path / "a.json")
    words = [word for word in printed.getvalue().split() if "/" not in word]  # file names may hold digits
    said = " ".join(words)
    assert re.search(r"\d{1,3}(,\d{3})+ ground triangles", said), said  # the counts here reach thousands
    assert not [word for word in words if re.fullmatch(r"\d{4,}", word.strip("│(),"))], said
