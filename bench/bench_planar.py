"""Planar benchmark speed (issue 17): ``mi-lidar benchmark-planar`` on the Intel CARMEN log, as a user runs it.

The command runs in a child process (imports, reading the log, leave-out maps, fitting and scoring
every model, writing the report) and is timed from start to exit. Target: the whole benchmark of a
~1000-scan log in under :data:`TIME_LIMIT_S` (the Intel log has 910 scans). Skipped when the shared
data folder is absent.
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


def run() -> list[dict]:
    """Time the command and return one row ``{"benchmark", "value", "target", "passed"}``."""
    label = "planar: mi-lidar benchmark-planar, Intel log (910 scans, all models), end to end"
    if not INTEL.is_file():
        return [{"benchmark": label, "value": f"data not found: {INTEL}", "target": "", "passed": None}]
    command = Path(sys.executable).with_name("mi-lidar")
    env = dict(os.environ, DRJIT_NUM_THREADS="2")
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="mi-lidar-bench-planar-") as out:
        start = time.perf_counter()
        done = subprocess.run(
            [str(command), "benchmark-planar", str(INTEL), "--out", out], env=env, capture_output=True, text=True
        )
        seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"benchmark-planar failed:\n{done.stderr[-2000:]}")
    load = f"load average {load_before:.1f} -> {os.getloadavg()[0]:.1f}"
    return [
        {
            "benchmark": f"{label} ({load})",
            "value": f"{seconds:.0f} s",
            "target": f"< {TIME_LIMIT_S:g} s",
            "passed": seconds < TIME_LIMIT_S,
        }
    ]


if __name__ == "__main__":
    for row in run():
        print(row)
