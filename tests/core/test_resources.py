"""Peak memory of a process is its own, even when a large process started it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import mi_lidar.core.resources as resources

PARENT_MIB = 512  # what the starting process holds when it starts the measured one

CHILD = f"""
import importlib.util, json, resource
spec = importlib.util.spec_from_file_location("resources", {str(Path(resources.__file__))!r})
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
inherited = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({{"own": module.peak_resident_mib(), "ru_maxrss": inherited}}))
"""

PARENT = f"""
import subprocess, sys
import numpy as np
held = np.ones({PARENT_MIB} * 2**17)  # {PARENT_MIB} MiB, every page touched
print(subprocess.run([sys.executable, "-c", {CHILD!r}], capture_output=True, text=True, check=True).stdout)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM and ru_maxrss's carry across exec are Linux's")
def test_a_process_started_by_a_large_one_reports_its_own_peak():
    out = subprocess.run([sys.executable, "-c", PARENT], capture_output=True, text=True, check=True).stdout
    child = json.loads(out.strip().splitlines()[-1])
    # the kernel's ru_maxrss carries the parent's peak into the child: the case the function must not fall for
    assert child["ru_maxrss"] > PARENT_MIB, child
    # a bare Python interpreter peaks at tens of MiB (measured ~10)
    assert 1 < child["own"] < 100, child


GROWTH = f"""
import importlib.util, json
import numpy as np
spec = importlib.util.spec_from_file_location("resources", {str(Path(resources.__file__))!r})
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
before = module.peak_resident_mib()
held = np.ones(256 * 2**17)  # 256 MiB, every page touched
print(json.dumps({{"before": before, "after": module.peak_resident_mib()}}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux's")
def test_the_peak_grows_by_what_the_process_allocates_in_mib():
    out = subprocess.run([sys.executable, "-c", GROWTH], capture_output=True, text=True, check=True).stdout
    peak = json.loads(out.strip().splitlines()[-1])
    assert 250 < peak["after"] - peak["before"] < 270, peak  # 256 MiB of data and a few pages of bookkeeping
