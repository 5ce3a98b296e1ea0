"""Write ``tests/data/regression_scans.npz``: reference scans that the refactors must reproduce.

Run only after a deliberate change of simulated scans (say which and why in the commit):

    .venv/bin/python tools/make_regression_scans.py              # every case
    .venv/bin/python tools/make_regression_scans.py indoor_planar  # only the named cases

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
    names = sys.argv[1:] or sorted(CASES)
    unknown = sorted(set(names) - set(CASES))
    if unknown:
        sys.exit(f"unknown case(s) {unknown}; the cases are {sorted(CASES)}")
    kept = np.load(OUT) if OUT.exists() and sys.argv[1:] else {}
    arrays = {key: kept[key] for key in getattr(kept, "files", []) if key.split("/", 1)[0] not in names}
    for name in names:
        for channel, values in simulate_case(name).items():
            arrays[f"{name}/{channel}"] = values
    partial = OUT.with_name(OUT.stem + ".partial.npz")
    np.savez_compressed(partial, **arrays)
    partial.replace(OUT)  # never leave a half-written reference
    print(f"wrote {OUT} ({OUT.stat().st_size / 1024:.0f} KiB, {len(arrays)} arrays)")
