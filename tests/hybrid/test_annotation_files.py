"""Annotation files: the documented example loads, and every bad file is refused naming the field and the file."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from mi_lidar.core.errors import SceneError
from mi_lidar.hybrid.compose import annotation_sensor, load_annotation
from mi_lidar.scene.files import write_mesh_ply

DOCS = Path(__file__).parents[2] / "docs" / "hybrid_scenes.md"
TREE = {"class": "small_tree", "center": [0, 0, 1], "yaw": 0.3, "extents": [1, 1, 2]}
IDENTITY = np.eye(4).ravel().tolist()


def documented_example() -> dict:
    section = DOCS.read_text().split("## Annotation files", 1)[1]
    return json.loads(re.search(r"```json\n(.*?)```", section, re.S).group(1))


def test_the_documented_example_loads(tmp_path):
    doc = documented_example()
    write_mesh_ply(tmp_path / doc["ground"], np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
    path = tmp_path / "a.json"
    path.write_text(json.dumps(doc))
    objects, ground = load_annotation(path)
    assert objects[0]["class"] == "small_tree" and objects[0]["center"] == (4.0, -2.5, 1.6)
    assert len(ground.faces) == 1
    sensor, poses = annotation_sensor(path)
    assert sensor.pattern == "vlp16" and poses.shape == (1, 4, 4) and sensor.pose[2, 3] == 1.8


def test_keys_of_other_tools_are_kept(tmp_path):
    path = tmp_path / "a.json"
    path.write_text(json.dumps({"format": "mi-lidar-annotation", "objects": [{**TREE, "segment": 7}]}))
    assert load_annotation(path)[0][0]["segment"] == 7


@pytest.mark.parametrize(
    "text, message",
    [
        ('{"format": "mi-lidar-annotation", "objects": [', r"not JSON"),
        ("[1, 2]", r"\(top level\): Input should be a valid dictionary"),
        ('{"format": "scene", "objects": []}', r"format: Input should be 'mi-lidar-annotation'"),
        ('{"format": "mi-lidar-annotation", "version": 9}', r"version: Input should be 1 \(got 9\)"),  # was read
        ('{"format": "mi-lidar-annotation", "objects": {"a": 1}}', r"objects: Input should be a valid list"),
        (
            json.dumps({"format": "mi-lidar-annotation", "objects": [{"class": "small_tree"}]}),
            r"objects\.0\.center: Field required",
        ),
        (
            json.dumps({"format": "mi-lidar-annotation", "objects": [{**TREE, "center": [0, 0, "x"]}]}),
            r"objects\.0\.center\.2: .*number",
        ),
        (
            json.dumps({"format": "mi-lidar-annotation", "objects": [{**TREE, "yaw": float("nan")}]}),
            r"objects\.0\.yaw: .*finite",
        ),
        (
            json.dumps({"format": "mi-lidar-annotation", "objects": [{**TREE, "extents": [1, -1, 2]}]}),
            r"objects\.0\.extents\.1: .*greater than or equal to 0",
        ),
        (
            json.dumps({"format": "mi-lidar-annotation", "objects": [{**TREE, "class": "oak"}]}),
            r"objects\.0\.class: .*unknown class 'oak'",
        ),
        (
            json.dumps({"format": "mi-lidar-annotation", "ground": "none.ply"}),
            r"ground: .*none\.ply: no such triangle mesh file",
        ),
        (
            json.dumps({"format": "mi-lidar-annotation", "ground": "junk.ply"}),
            r"ground: .*junk\.ply: not a triangle mesh PLY",
        ),
    ],
)
def test_bad_annotations_name_the_file_and_the_field(tmp_path, text, message):
    (tmp_path / "junk.ply").write_text("not a ply")
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(SceneError, match="(?s)" + re.escape(str(path)) + ".*" + message):
        load_annotation(path)


@pytest.mark.parametrize(
    "sensor, message",
    [
        ({"pattern": "vlp16", "poses": [IDENTITY, [1, 2, 3]]}, r"sensor\.poses: .*pose 1 has 3 numbers"),
        ({"pattern": "vlp16", "poses": [[2.0, *IDENTITY[1:]]]}, r"sensor\.poses: pose 0 is not a rigid transform"),
        ({"pattern": "vlp16", "max_range": 0}, r"sensor\.max_range: .*greater than 0"),
        ({"poses": [IDENTITY]}, r"sensor\.pattern: Field required"),
    ],
)
def test_bad_sensors_name_the_field(tmp_path, sensor, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"format": "mi-lidar-annotation", "objects": [TREE], "sensor": sensor}))
    with pytest.raises(SceneError, match=message):
        annotation_sensor(path)
