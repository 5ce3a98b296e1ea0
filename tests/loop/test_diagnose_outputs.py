"""diagnose hands back what it found: an HTML report and the scene XML with the model's effects."""

import mitsuba as mi
import numpy as np
from typer.testing import CliRunner

from mi_lidar.cli import app
from mi_lidar.scene import load_scene, scene_sensor_model
from mi_lidar.scene.files import scene_with_effects

from ..conftest import SCENES
from .helpers import hidden_log, room


def test_diagnose_writes_html_and_the_scene_with_the_found_effect(tmp_path, monkeypatch):
    """A hidden 5 cm range bias is found; out/scene.xml loads from another folder and carries it (seeded; the
    bias refits within 1 cm)."""
    scene, model, poses = room(6)
    log, _ = hidden_log(scene, model, poses, "range_bias(bias=0.05)")
    log.save(tmp_path / "room.npz")
    result = CliRunner().invoke(
        app,
        [
            "diagnose",
            str(tmp_path / "room.npz"),
            str(SCENES / "indoor_planar.xml"),
            "--out",
            str(tmp_path / "d"),
            "--candidate",
            "range_bias",
            "--candidate",
            "outliers",
        ],
        terminal_width=200,
    )
    assert result.exit_code == 0, result.stdout
    assert "range_bias" in (tmp_path / "d" / "diagnosis.html").read_text()
    monkeypatch.chdir(tmp_path)  # the copy's file references are absolute
    found, _ = scene_sensor_model(load_scene(tmp_path / "d" / "scene.xml"))
    bias = [e for e in found.effects if e.name == "range_bias"]
    assert bias and abs(float(np.mean(np.asarray(bias[0].params["bias"]))) - 0.05) < 0.01


def test_scene_with_effects_replaces_an_existing_effects_string(tmp_path):
    text = (SCENES / "indoor_planar.xml").read_text()
    first = scene_with_effects(SCENES / "indoor_planar.xml", "range_bias(bias=0.02)", tmp_path / "a.xml")
    second = scene_with_effects(first, "outliers(p_near=0.01)", tmp_path / "b.xml")
    out = second.read_text()
    assert out.count('name="effects"') == 1 and "outliers(p_near=0.01)" in out and "range_bias" not in out
    assert out.count("<integrator") == text.count("<integrator")
    model, _ = scene_sensor_model(mi.load_file(str(second)))
    assert [e.name for e in model.effects] == ["outliers"]
