"""A command ended by SIGTERM (``kill``, ``timeout``, a cancelled CI job) cleans up as after Ctrl-C or an error."""

import os
import signal
import subprocess
import sys
import time

import pytest

from .planar.world import room_log_text

# The child runs benchmark-planar with the stage named by argv[1] replaced by a wait: it writes argv[2] when it
# gets there, so the test sends SIGTERM while the command is in that stage.
CHILD = """
import pathlib, sys, time
import mi_lidar.planar.benchmark as benchmark
import mi_lidar.planar.report as report
from mi_lidar.cli import app

stage, ready = sys.argv[1], pathlib.Path(sys.argv[2])

def wait(*args, **kwargs):
    ready.write_text("in " + stage)
    time.sleep(3600)

if stage == "run":
    benchmark.run_planar_benchmark = wait
else:
    report.range_figure = wait  # after the JSON and two figures are written into the staging folder
app(sys.argv[3:])
"""


def listing(folder) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("stage", ["run", "write"])
def test_sigterm_leaves_no_new_folder_and_no_staged_report(tmp_path, stage):
    """SIGTERM while the benchmark ran left its new, empty --out folder; while it wrote its report into an --out that
    held the previous one, it left a hidden staging folder there (.benchmark-huzguqnr/ with benchmark.json, nll.png,
    residuals.png and an empty temporary PNG), never removed. Python's default SIGTERM ends the process before any
    clean-up runs."""
    (tmp_path / "room.log").write_text(room_log_text(scans=30))
    out = tmp_path / ("new" if stage == "run" else "previous")
    if stage == "write":
        out.mkdir()
        (out / "benchmark.json").write_text("{}")  # the previous report
    before = listing(out) if out.exists() else None
    ready = tmp_path / "ready"
    args = ["benchmark-planar", tmp_path / "room.log", "--out", out, "-m", "M0", "--window", "5"]
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, stage, ready, *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    while not ready.exists() and child.poll() is None:
        time.sleep(0.1)
    assert child.poll() is None, child.communicate()[0]
    os.kill(child.pid, signal.SIGTERM)
    output = child.communicate()[0]
    assert child.returncode == 128 + signal.SIGTERM, (child.returncode, output)
    assert "Traceback" not in output, output
    if before is None:
        assert not out.exists(), list(out.iterdir())
    else:
        assert listing(out) == before and [p.name for p in out.iterdir()] == ["benchmark.json"]
