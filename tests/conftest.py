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


def pytest_runtest_logreport(report):
    """Collect the parameters that passing finite-difference checks verified (``fd_checked`` properties; under
    xdist the workers' reports reach the controller with their properties)."""
    if report.when == "call" and report.passed:
        _FD_CHECKED.extend(value for name, value in report.user_properties if name == "fd_checked")


def pytest_terminal_summary(terminalreporter):
    """Print how many catalog parameters the finite-difference checks verified."""
    if _FD_CHECKED:
        cases = {name.split(".")[0] for name in _FD_CHECKED}
        terminalreporter.write_line(
            f"finite-difference gradient checks: {len(_FD_CHECKED)} parameters of {len(cases)} catalog cases "
            "(effect variants and densities)"
        )


def rays_along_x(n: int):
    """``n`` rays from the origin along +x (beam 0, time 0, ray ids 0..n-1): a :class:`RayBatch` for unit tests."""
    import drjit as dr
    import mitsuba as mi

    import mi_lidar  # noqa: F401  (sets up LLVM before Dr.Jit loads)
    from mi_lidar.core.rays import RayBatch

    return RayBatch(
        origin=mi.Point3f(0, 0, 0),
        direction=mi.Vector3f(1, 0, 0),
        beam=dr.zeros(mi.UInt32, n),
        time=dr.zeros(mi.Float, n),
        ray_id=dr.arange(mi.UInt32, n),
    )
