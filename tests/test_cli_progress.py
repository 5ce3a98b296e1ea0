"""Progress on non-terminal output: plain lines on stderr at a bounded rate, and the time taken at the end."""

import numpy as np
from typer.testing import CliRunner

from mi_lidar.cli import app
from mi_lidar.cli import progress as progress_module

from .conftest import SCENES


def test_simulate_prints_plain_progress_lines_when_not_a_terminal(tmp_path, monkeypatch):
    monkeypatch.setattr(progress_module, "PLAIN_EVERY_S", 0.0)  # every update prints
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 2, 3] = 0.5
    np.save(tmp_path / "poses.npy", poses)
    args = ["simulate", str(SCENES / "indoor_planar.xml"), "--poses", str(tmp_path / "poses.npy")]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "room.npz")])
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    assert "simulating scans: 3/3" in " ".join(lines)
    assert any(line.startswith("simulating scans: done (") for line in lines)
    assert "simulating scans" not in result.stdout  # progress is not a result
    assert "\x1b[" not in result.output  # no terminal control codes in a log


def test_plain_lines_are_rate_limited(monkeypatch, capsys):
    clock = iter(np.arange(0.0, 100.0, 1.0))  # one second per call of the timer
    monkeypatch.setattr(progress_module.time, "perf_counter", lambda: float(next(clock)))
    with progress_module.progress("work", total=40) as update:
        for done in range(1, 41):
            update(done)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("work")]
    # First update, then every 10 s (10 calls), the last one, and the closing line.
    assert (
        lines[0].startswith("work: 1/40") and lines[-2].startswith("work: 40/40") and lines[-1].startswith("work: done")
    )
    assert 5 <= len(lines) <= 7
