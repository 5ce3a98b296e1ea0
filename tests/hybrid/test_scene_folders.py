"""A written hybrid scene's folder moves whole: its XML names the pattern table and the PLY assets relative to itself,
so a folder renamed, moved or shared still loads and renders."""

import json

import mitsuba as mi
import numpy as np

import mi_lidar
from mi_lidar.core.patterns import get_pattern, to_table
from mi_lidar.hybrid import commands, experiment

from .libraries import small_library

TREE = {"class": "small_tree", "center": [6.0, 0.0, 1.0], "yaw": 0.0, "extents": [1.0, 1.0, 2.5]}


def loads_and_sees(xml) -> float:
    """The share of beams that return in ``mi.render`` of the scene at ``xml``, loaded by Mitsuba's own loader."""
    scene = mi.load_file(str(xml))
    image = np.asarray(mi.render(scene))
    return float(np.mean(image[..., 1] > 0))


def test_a_composed_scene_loads_after_its_folder_is_renamed(tmp_path):
    """compose wrote the absolute path of the annotation's pattern table into the XML: once the folder was renamed,
    the scene named a file that was gone."""
    project = tmp_path / "project"
    small_library(project / "lib")
    to_table(get_pattern("vlp16", n_firings=90), project / "ann_pattern.npy")
    pose = np.eye(4)
    pose[2, 3] = 1.0
    sensor = {"pattern": "ann_pattern.npy", "poses": [pose.ravel().tolist()], "min_range": 0.0, "max_range": 80.0}
    annotation = project / "ann.json"
    annotation.write_text(json.dumps({"format": "mi-lidar-annotation", "objects": [TREE], "sensor": sensor}))
    xml, *files = commands.compose(annotation, project / "lib", project / "scene" / "c.xml", preview=False)
    project.rename(tmp_path / "shared")
    moved = tmp_path / "shared" / "scene" / "c.xml"
    assert loads_and_sees(moved) > 0.0  # the tree, 6 m ahead
    assert mi_lidar.load_scene(moved).sensors()[0].pattern.shape == (16, 90)
    assert str(tmp_path) not in moved.read_text()
    assert xml.parent / "c_assets" / "pattern.npy" in files  # the table is the scene's own, in its assets


def test_the_experiment_scenes_load_after_their_folder_is_renamed(tmp_path, small_fit, small_log):
    """python -m mi_lidar.hybrid.experiment wrote the log's pattern table by its absolute path, as compose did."""
    xml = experiment._write(small_fit.model, tmp_path / "out" / "train_scene", "train", small_log)
    (tmp_path / "out").rename(tmp_path / "moved")
    moved = tmp_path / "moved" / "train_scene" / xml.name
    assert loads_and_sees(moved) > 0.2
    assert str(tmp_path) not in moved.read_text()
