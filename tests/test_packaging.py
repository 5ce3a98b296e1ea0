"""The built wheel works outside the source tree: it ships the bundled scenes and `mi-lidar demo` runs."""

import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_installs_into_a_fresh_venv_and_runs_the_demo(tmp_path):
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(REPO)], check=True)
    (wheel,) = wheels.glob("mi_lidar-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    bundled = [p.relative_to(REPO).as_posix() for p in (REPO / "scenes_xml").rglob("*") if p.suffix in (".xml", ".ply")]
    assert bundled and all(f"mi_lidar/{name}" in names for name in bundled)
    venv.create(tmp_path / "venv", with_pip=True)
    python = tmp_path / "venv" / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "-q", str(wheel)], check=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    result = subprocess.run(
        [str(tmp_path / "venv" / "bin" / "mi-lidar"), "demo", "--out", "demo_out"],
        cwd=work,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert (work / "demo_out" / "scan.npz").is_file()
    assert "NLL per ray" in result.stdout
