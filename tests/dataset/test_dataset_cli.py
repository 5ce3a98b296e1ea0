"""The ``dataset`` verb's output in a log (not a terminal): plain progress lines on stderr, none before the scene
check."""

from typer.testing import CliRunner

from mi_lidar.cli import app
from mi_lidar.cli import progress as progress_module
from tests.conftest import SCENES

SPEC = """
name: cli
seed: 3
rig:
  lidars: [{name: top, pattern: vlp16, mount: {xyz: [0, 0, 1.8]}}]
  cameras: [{name: front, width: 32, height: 20, mount: {xyz: [0.5, 0, 1.6]}}]
scenes:
  - name: street
    xml: XML
    frames: 2
    labels: {LABELS}
    trajectory: {waypoints: [[-6, 0], [4, 0]]}
output: {spp: 1}
"""
LABELS = "1: road, 2: building, 3: pole, 4: car, 6: vegetation"


def run(tmp_path, labels: str):
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC.replace("XML", str(SCENES / "urban_street.xml")).replace("LABELS", labels))
    return CliRunner().invoke(app, ["dataset", str(spec), "--out", str(tmp_path / "out"), "--serial"])


def test_a_run_in_a_log_prints_frame_counts_and_the_time_taken(tmp_path, monkeypatch):
    monkeypatch.setattr(progress_module, "PLAIN_EVERY_S", 0.0)  # every update prints
    result = run(tmp_path, LABELS)
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("cli: 2 frames from 1 scene -> "), result.stdout  # it said '1 scenes'
    assert not [line for line in result.stdout.splitlines() if line.startswith("frames")]  # progress is not a result
    lines = result.stderr.splitlines()
    assert [line.split(" (")[0] for line in lines if line.startswith("frames: ")] == [
        "frames: 0/2",
        "frames: 1/2",
        "frames: 2/2",
        "frames: done",
    ]
    assert "\x1b[" not in result.output  # no terminal control codes in a log


def test_a_scene_refused_by_the_check_prints_no_frame_count(tmp_path, monkeypatch):
    monkeypatch.setattr(progress_module, "PLAIN_EVERY_S", 0.0)
    result = run(tmp_path, "1: road, 2: building")  # labels 3, 4 and 6 have no class name
    assert result.exit_code == 2, result.output
    assert "have no class name" in result.output
    assert not [line for line in result.output.splitlines() if line.startswith("frames")], result.output


def test_a_cut_spec_is_one_error_line_naming_line_and_column(tmp_path):
    """ruamel's error spread over five lines with a drawing of the spot ('while parsing a flow node ... ^')."""
    spec = tmp_path / "spec.yaml"
    text = SPEC.replace("XML", str(SCENES / "urban_street.xml")).replace("LABELS", LABELS)
    spec.write_text(text[: text.index("[4, 0]]") + 3])  # cut inside the trajectory
    result = CliRunner().invoke(app, ["dataset", str(spec), "--out", str(tmp_path / "out"), "--serial"])
    assert result.exit_code == 2, result.output
    said = " ".join(result.output.split())
    problem = "line 12, column 42: expected the node content, but found '<stream end>'"
    assert f"spec.yaml: cannot parse the spec: {problem}" in said, said
    assert result.output.count("error:") == 1 and "^" not in result.output and "while" not in said, result.output
