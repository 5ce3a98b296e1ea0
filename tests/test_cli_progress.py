"""Progress on non-terminal output: plain lines on stderr at a bounded rate, and the time taken at the end."""

import io

import numpy as np
from rich.console import Console
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


def short_run(update, estimate: int = 532) -> None:
    """Work whose total was an estimate (evaluate-apps-3d's (draws + 60) * sources) and that ends at 174."""
    for done in range(1, 175):
        update(done, estimate, "evaluating")


def test_a_plain_count_that_ends_short_of_its_total_ends_at_what_it_reached(monkeypatch, capsys):
    monkeypatch.setattr(progress_module, "PLAIN_EVERY_S", 1e9)  # only the first and the closing lines print
    with progress_module.progress("evaluate-apps-3d frame.pcap") as update:
        short_run(update)
    lines = [line for line in capsys.readouterr().err.splitlines() if line]
    assert lines[0].startswith("evaluating: 1/532 (")
    assert lines[-2].startswith("evaluating: 174/174 (")  # it said 174/532, then done
    assert lines[-1].startswith("evaluate-apps-3d frame.pcap: done (")


def test_a_bar_that_ends_short_of_its_total_ends_full(monkeypatch):
    out = io.StringIO()
    monkeypatch.setattr(progress_module, "console", Console(file=out, force_terminal=True, width=80))
    with progress_module.progress("calibrating", total=532) as update:  # an early stop at step 174
        short_run(update)
    assert "174/174" in out.getvalue()  # the bar's last frame: full, at the count it reached
