"""Write ``tests/data/regression_scans.npz``: reference scans that the refactors must reproduce.

Run only after a deliberate change of simulated scans (say which and why in the commit):

    .venv/bin/python tools/make_regression_scans.py

The cases are in ``tests/regression_cases.py``; the test ``tests/test_regression_scans.py`` simulates
them again and compares channel by channel.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, for tests.regression_cases

from tests.regression_cases import CASES, simulate_case

OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "regression_scans.npz"

if __name__ == "__main__":
    arrays = {}
    for name in CASES:
        for channel, values in simulate_case(name).items():
            arrays[f"{name}/{channel}"] = values
    np.savez_compressed(OUT, **arrays)
    print(f"wrote {OUT} ({OUT.stat().st_size / 1024:.0f} KiB, {len(arrays)} arrays)")
