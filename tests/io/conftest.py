"""Shared helpers for the I/O tests: files of the real-data folder ``../shared/data``."""

from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def data_file(relative: str) -> Path:
    """Path of one file under ``../shared/data``; skips the test when it is absent."""
    path = DATA / relative
    if not path.is_file():
        pytest.skip(f"real data file {path} is absent (tests read ../shared/data relative to the repo root)")
    return path
