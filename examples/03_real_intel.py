"""The loop on real data: the Intel lab log scored with leave-out maps (docs/loop_results.md, "Real data").

Run:  python examples/03_real_intel.py [N_TEST]
It builds the 5 cm count map of ../shared/data/carmen/intel-corrected.log.gz, a leave-out map per
test scan (every 5th scan; scans within 1 m and 30 s left out) and per calibration scan (which
also leave out every test scan), scores the baselines and the permeable map with effects added
one by one (fitted on calibration scans only), and prints the development path in nats per
test beam (1 cm range bins). N_TEST limits the test and calibration scans (default: all 182).
It takes several minutes.
"""

import sys
import time
from pathlib import Path

from rich.console import Console

import mi_lidar  # noqa: F401  (selects the variant, registers the plugins)
from mi_lidar.io.carmen import read_carmen
from mi_lidar.loop.real_data import IntelData, development_table, intel_development_path

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "carmen" / "intel-corrected.log.gz"

if __name__ == "__main__":
    console = Console()
    limit = int(sys.argv[1]) if len(sys.argv) > 1 else None
    start = time.perf_counter()
    say = lambda message: console.log(f"[{time.perf_counter() - start:6.1f} s] {message}")  # noqa: E731
    data = IntelData(read_carmen(DATA))
    say(f"count map: grid {data.grid.shape} of {data.grid.cell} m, {len(data.test)} test scans")
    rows = intel_development_path(data, n_test=limit, n_train=limit, progress=say)
    console.print(development_table(rows, "Intel lab, nats per test beam (1 cm bins); references 5.01 / 4.24 / 3.63"))
    console.print("final parameters: " + ", ".join(f"{k}={v:.4g}" for k, v in rows[-1].fitted.items()))
