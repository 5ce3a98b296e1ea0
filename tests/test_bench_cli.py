"""The benchmark runner's command line: help and bad names, without running a benchmark."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_help_describes_the_runner_and_runs_nothing():
    done = run_bench("--help")
    assert done.returncode == 0
    assert "usage: python -m bench" in done.stdout and "--only" in done.stdout and "planar" in done.stdout
    assert "targets met" not in done.stdout


def test_an_unknown_benchmark_is_named_with_the_choices():
    done = run_bench("--only", "terrain")
    assert done.returncode == 2
    assert "'terrain'" in done.stderr and "planar" in done.stderr
