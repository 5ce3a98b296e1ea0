"""The same seed gives the same scan in every channel, also when several processes load scenes at once.

Mitsuba loads shapes in parallel and lists them in the order its threads finished, which changes
under load; element and shape ids must come from the scene's declared ids instead. Three processes
load and render two scenes four times each at the same time (permeable layers: four named sheets; the street: cubes that
share a material, which Mitsuba would otherwise merge into one unnamed mesh) and print a digest of
every channel; all digests must agree.
"""

import json
import subprocess
import sys

import numpy as np

import mi_lidar
from mi_lidar.core.scene_shapes import ordered_shapes

from .conftest import SCENES

RENDER_DIGESTS = """
import hashlib, json, sys
import mitsuba as mi
import mi_lidar
from mi_lidar.core.channels import tensor_to_numpy
loads = []
for _ in range(int(sys.argv[1])):
    digests = {}
    for name in sys.argv[2:]:
        channels = tensor_to_numpy(mi.render(mi_lidar.load_scene(name), seed=1))
        digests.update({f"{name}/{k}": hashlib.sha256(v.tobytes()).hexdigest() for k, v in channels.items()})
    loads.append(digests)
print(json.dumps(loads))
"""
PROCESSES = 3
LOADS = 4  # per process: the loader's order also varies between loads in one process


def test_concurrent_renders_agree_in_every_channel():
    scenes = [str(SCENES / "permeable_layers.xml"), str(SCENES / "urban_street.xml")]
    runs = [
        subprocess.Popen([sys.executable, "-c", RENDER_DIGESTS, str(LOADS), *scenes], stdout=subprocess.PIPE, text=True)
        for _ in range(PROCESSES)
    ]
    digests = [load for run in runs for load in json.loads(run.communicate()[0])]
    assert all(run.returncode == 0 for run in runs)
    assert {"element_id", "shape_id", "range", "hit", "label"} <= {key.split("/")[-1] for key in digests[0]}
    for other in digests[1:]:
        assert other == digests[0], [key for key in digests[0] if other[key] != digests[0][key]]


def test_shapes_keep_their_declared_ids():
    scene = mi_lidar.load_scene(SCENES / "urban_street.xml")
    ids = [shape.id() for shape in ordered_shapes(scene)]
    assert ids == sorted(ids)
    assert {"building_north_a", "building_south_b", "car_body", "car_cabin", "road"} <= set(ids)


def test_element_ids_follow_the_declared_ids():
    channels = mi_lidar.simulate(mi_lidar.load_scene(SCENES / "permeable_layers.xml"), seed=1).attributes
    shape, label = channels["shape_id"][channels["shape_id"] >= 0], channels["label"][channels["shape_id"] >= 0]
    # layer_1, layer_2, layer_3, wall carry labels 1..4 in the XML: shape k has label k + 1.
    np.testing.assert_array_equal(label, shape + 1)
