"""The loop on real data: every sensor model scored on the Intel lab log by the planar benchmark.

Run:  python examples/03_real_intel.py [OUT]
It runs the real-planar protocol (``mi-lidar benchmark-planar``, :mod:`mi_lidar.planar.benchmark`) on
../shared/data/carmen/intel-corrected.log.gz: every 5th scan is a test scan, each scan's 5 cm map
leaves out the scans within 1 m and 30 s of it, every model is fitted on training scans only and
scored on the test beams (nats per beam, 1 cm bins) beside the realism of a sampled scan. The report
(benchmark.html, benchmark.json, PNGs) goes to OUT (default: reports/intel). About 3 minutes on
2 cores. The same command works on any planar CARMEN log: see docs/loop_results.md.
"""

import argparse
import sys
from pathlib import Path

from mi_lidar.cli import app

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "carmen" / "intel-corrected.log.gz"

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", nargs="?", default="reports/intel", help="report folder (default: %(default)s)")
    out = parser.parse_args().out
    if not DATA.is_file():
        sys.exit(f"the Intel log is not at {DATA.resolve()}: it lives beside the repository in ../shared/data")
    app(["benchmark-planar", str(DATA), "--out", out])  # prints progress, the table and the report path
