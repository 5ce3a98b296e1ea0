"""Planar benchmark speed (issue 17): ``mi-lidar benchmark-planar`` on the Intel CARMEN log, as a user runs it.

The command runs in a child process (imports, reading the log, leave-out maps, fitting and scoring
every model, writing the report) and is timed from start to exit; its peak memory (maximum resident set
size, from a small launcher process: :data:`LAUNCHER`) is reported beside the time. Target: the whole benchmark of a
~1000-scan log in under :data:`TIME_LIMIT_S` (the Intel log has 910 scans of 180 beams). A second row
runs it on the same log resampled to 361 beams (``tools/derive_carmen.py --beams 361 --resample
nearest --clip 50``: a 361-beam SICK scanner clipping at 50 m, twice the beams of the first row).
Skipped when the shared data folder is absent.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

INTEL = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen" / "intel-corrected.log.gz"
TIME_LIMIT_S = 300.0  # 5 minutes per ~1000-scan log


DERIVE = Path(__file__).resolve().parents[1] / "tools" / "derive_carmen.py"
# Runs the command and prints its peak resident set size (KiB). A child forked from this (large) process
# would count the parent's pages in its ru_maxrss, which exec does not reset; the launcher is small when it
# forks the command.
LAUNCHER = (
    "import resource, subprocess, sys; "
    "code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode; "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(code)"
)


def run() -> list[dict]:
    """Time the command on both logs and return the rows ``{"benchmark", "value", "target", "passed"}``."""
    label = "planar: mi-lidar benchmark-planar, Intel log ({}, all models), end to end"
    if not INTEL.is_file():
        return [{"benchmark": label.format("910 scans"), "value": f"data not found: {INTEL}", "target": ""}]
    with tempfile.TemporaryDirectory(prefix="mi-lidar-bench-planar-") as folder:
        derived = Path(folder) / "intel-361.log.gz"
        made = subprocess.run(
            [sys.executable, str(DERIVE), str(INTEL), str(derived), "--beams", "361", "--resample", "nearest"]
            + ["--clip", "50"],
            capture_output=True,
            text=True,
        )
        if made.returncode != 0:
            raise RuntimeError(f"derive_carmen.py failed:\n{made.stderr[-2000:]}")
        return [
            _timed(INTEL, label.format("910 scans x 180 beams")),
            _timed(derived, label.format("910 scans resampled to 361 beams, clipped at 50 m")),
        ]


def _timed(log: Path, label: str) -> dict:
    """Run ``mi-lidar benchmark-planar LOG`` in a child process; its row."""
    command = Path(sys.executable).with_name("mi-lidar")
    env = dict(os.environ, DRJIT_NUM_THREADS="2")
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="mi-lidar-bench-planar-") as out, tempfile.TemporaryFile() as err:
        start = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-c", LAUNCHER, str(command), "benchmark-planar", str(log), "--out", out],
            env=env,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
        )
        seconds = time.perf_counter() - start
        err.seek(0)
        if done.returncode != 0:
            raise RuntimeError(f"benchmark-planar failed on {log.name}:\n{err.read().decode()[-2000:]}")
    peak_kib = int(done.stdout.split()[-1])
    load = f"load average {load_before:.1f} -> {os.getloadavg()[0]:.1f}"
    return {
        "benchmark": f"{label} ({load})",
        "value": f"{seconds:.0f} s; peak memory {peak_kib / 2**20:.2f} GB",
        "target": f"< {TIME_LIMIT_S:g} s",
        "passed": seconds < TIME_LIMIT_S,
    }


if __name__ == "__main__":
    for row in run():
        print(row)
