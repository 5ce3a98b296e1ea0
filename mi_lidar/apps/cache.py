"""The evaluations' dataset cache: the states and every source's scans of one run, in one ``.npz``.

A cache belongs to its input file, its settings and the code that wrote it (:func:`cache_key`); a file
written for other ones is ignored, so a run stopped half-way resumes with the same code and never mixes
scans of an older version into a newer one. The file is written atomically, so a run stopped half-way
leaves either the old cache or the new one.
"""

from __future__ import annotations

import hashlib
from functools import cache
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.strict_json import dumps_exact, loads_exact


def cache_key(path: Path, settings: dict) -> str:
    """The SHA-256 of the input file's bytes, the settings (:func:`~mi_lidar.core.strict_json.dumps_exact`, sorted keys:
    an infinite setting and a NaN one differ) and :func:`code_digest`."""
    data = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return f"{data}|{dumps_exact(settings, sort_keys=True)}|code {code_digest()}"


@cache
def code_digest() -> str:
    """:func:`source_digest` of the installed ``mi_lidar`` package (computed once per process)."""
    import mi_lidar

    return source_digest(Path(mi_lidar.__file__).resolve().parent)


def source_digest(root: Path) -> str:
    """The SHA-256 of every Python file under ``root``: their relative paths and bytes, in path order."""
    digest = hashlib.sha256()
    for file in sorted(Path(root).rglob("*.py")):
        digest.update(file.relative_to(root).as_posix().encode())
        digest.update(file.read_bytes())
    return digest.hexdigest()


def save_datasets(file: Path, key: str, states: dict, ranges: dict, benchmark: list[dict]) -> None:
    """Write the state arrays ``states``, the (name -> array) scans ``ranges`` and the benchmark rows."""
    arrays = {
        "key": np.array(key),
        "benchmark": np.array(dumps_exact({"rows": benchmark}, default=float)),
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
        return states, {name: z[f"ranges/{name}"] for name in names}, loads_exact(str(z["benchmark"]))["rows"]
