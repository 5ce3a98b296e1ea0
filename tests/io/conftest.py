"""Shared fixtures for the I/O tests: the real-data folder ``../shared/data``."""

from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real measured data folder; skips the test when it is absent."""
    if not DATA.is_dir():
        pytest.skip(f"real Lidar data folder {DATA} is absent (see DEVELOPERS.md: ../shared/data)")
    return DATA


def data_file(relative: str) -> Path:
    """Path of one file under ``../shared/data``; skips the test when it is absent."""
    path = DATA / relative
    if not path.is_file():
        pytest.skip(f"real data file {path} is absent (tests read ../shared/data relative to the repo)")
    return path
