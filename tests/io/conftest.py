"""Shared helpers for the I/O tests: files of the real-data folder ``../shared/data``."""

import os
from pathlib import Path

import pytest

OUSTER_SDK_ENV = "MI_LIDAR_OUSTER_SDK_DATA"

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def data_file(relative: str) -> Path:
    """Path of one file under ``../shared/data``; skips the test when it is absent."""
    path = DATA / relative
    if not path.is_file():
        pytest.skip(f"real data file {path} is absent (tests read ../shared/data relative to the repo root)")
    return path


def ouster_sdk_file(name: str) -> Path:
    """A file fetched by ``tools/fetch_ouster_sdk_data.py``; skips the test when it is absent."""
    folder = Path(os.environ.get(OUSTER_SDK_ENV, DATA / "ouster-sdk"))
    path = folder / name
    if not path.is_file():
        pytest.skip(
            f"Ouster SDK test file {path} is absent; run `python tools/fetch_ouster_sdk_data.py` "
            f"(or set ${OUSTER_SDK_ENV})"
        )
    return path
