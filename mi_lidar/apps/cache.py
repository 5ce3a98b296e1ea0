"""The evaluations' dataset cache: the states and every source's scans of one run, in one ``.npz``.

A cache belongs to its input file and settings (:func:`cache_key`); a file written for other ones is
ignored, and the file is written atomically, so a run stopped half-way leaves either the old cache or
the new one.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path


def cache_key(path: Path, settings: dict) -> str:
    """The SHA-256 of the input file's bytes and the settings (JSON, sorted keys)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest() + "|" + json.dumps(settings, sort_keys=True)


def save_datasets(file: Path, key: str, states: dict, ranges: dict, benchmark: list[dict]) -> None:
    """Write the state arrays ``states``, the (name -> array) scans ``ranges`` and the benchmark rows."""
    arrays = {
        "key": np.array(key),
        "benchmark": np.array(json.dumps(benchmark, default=float)),
        **states,
        "sources": np.array(list(ranges)),
        **{f"ranges/{name}": value for name, value in ranges.items()},
    }
    with atomic_path(file) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def load_datasets(file: Path, key: str) -> tuple[dict, dict, list[dict]] | None:
    """``(state arrays, ranges, benchmark rows)`` written by :func:`save_datasets`; None when absent or stale."""
    if not file.exists():
        return None
    with np.load(file) as z:
        if str(z["key"]) != key:
            return None
        names = [str(name) for name in z["sources"]]
        states = {k: z[k] for k in z.files if k not in ("key", "benchmark", "sources") and not k.startswith("ranges/")}
        return states, {name: z[f"ranges/{name}"] for name in names}, json.loads(str(z["benchmark"]))
