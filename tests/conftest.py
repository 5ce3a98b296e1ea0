"""Shared fixtures: the repository paths and the real-data folder."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "scenes_xml"
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()


@pytest.fixture
def shared_data() -> Path:
    """The real measured data folder; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it lives beside the repository in ../shared/data)")
    return SHARED_DATA


_FD_CHECKED: list[str] = []


@pytest.fixture
def fd_counter() -> list[str]:
    """Collects the parameters a finite-difference check covered (reported at the end of the run)."""
    return _FD_CHECKED


def pytest_terminal_summary(terminalreporter):
    """Print how many catalog parameters the finite-difference checks covered in this process."""
    if _FD_CHECKED:
        names = sorted({name.split(".")[0] for name in _FD_CHECKED})
        terminalreporter.write_line(
            f"finite-difference gradient checks: {len(_FD_CHECKED)} parameters of {len(names)} effects and densities"
        )
