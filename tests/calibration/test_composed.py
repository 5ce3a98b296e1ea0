"""A scene composed from a primitive library and an annotation becomes calibration element sets.

The sets load as a scene dict, simulate, save as XML + PLY and reload unchanged; every object
gets its own parameter names, and a hit probability of one object is recovered by calibration.
"""

import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import SceneError
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.hybrid.classes import CLASS_ID
from mi_lidar.hybrid.compose import save_annotation
from mi_lidar.hybrid.element_sets import composed_element_sets, hybrid_element_sets
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh
from mi_lidar.hybrid.primitives import Primitive, PrimitiveLibrary
from mi_lidar.scene.dicts import save_scene, scene_dict

from .scenes import pattern


def primitive(name: str, label: int, means, sigma: float, p_hit: float) -> Primitive:
    means = np.asarray(means, float)
    covs = np.tile(np.diag([sigma**2, (0.8 * sigma) ** 2, (1.3 * sigma) ** 2]), (len(means), 1, 1))
    ellipsoids = EllipsoidSet(means, covs, np.full(len(means), p_hit), label=label)
    return Primitive(name, label, ellipsoids, means.min(0) - 3 * sigma, means.max(0) + 3 * sigma)


@pytest.fixture(scope="module")
def composed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("composed")
    library = PrimitiveLibrary(
        [
            primitive("tree", CLASS_ID["small_tree"], [[0, 0, 0.5], [0, 0, 1.5], [0.3, 0.2, 2.3]], 0.35, 0.4),
            primitive("rock", CLASS_ID["rock"], [[0, 0, 0], [0.4, 0, 0.1]], 0.25, 0.9),
        ]
    )
    library.save(tmp / "library")
    g = np.linspace(-15, 15, 7)
    x, y = np.meshgrid(g, g, indexing="ij")
    i, j = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    a, b, c, d = i * 7 + j, (i + 1) * 7 + j, (i + 1) * 7 + j + 1, i * 7 + j + 1
    ground = GroundMesh(
        np.c_[x.ravel(), y.ravel(), np.zeros(49)],
        np.r_[np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)],
        p_hit=0.95,
        range_sigma=0.02,
        label=CLASS_ID["ground"],
    )
    objects = [
        {"class": "small_tree", "center": [5.0, 0.0, 1.4], "yaw": 0.3, "extents": [1.5, 1.5, 3.0]},
        {"class": "rock", "center": [0.0, -4.0, 0.2], "yaw": 1.0, "extents": [1.0, 0.8, 0.5]},
        {"class": "small_tree", "center": [-4.0, 3.0, 1.4], "yaw": -0.5, "extents": [1.5, 1.5, 3.0]},
        {"class": "large_tree", "center": [9.0, 9.0, 4.0], "yaw": 0.0, "extents": [4.0, 4.0, 8.0]},
    ]
    annotation, *_ = save_annotation(tmp / "annotation.json", objects, ground)
    return tmp, annotation, tmp / "library"


def sensor_pose():
    pose = np.eye(4)
    pose[2, 3] = 1.6
    return pose


def test_one_set_per_object_and_ground(composed):
    _, annotation, library = composed
    sets = composed_element_sets(annotation, library)
    assert list(sets) == ["ground", "small_tree_0", "rock_1", "small_tree_2"]  # the large tree is not in the library
    assert (
        len(sets["ground"].faces) == 72 and len(sets["small_tree_0"].centers) == 3 and len(sets["rock_1"].centers) == 2
    )
    # Primitive ellipsoids are rotated by the object's yaw and moved to its center.
    yaw = np.array([[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])
    local_mean = np.array([0.3, 0.2, 4.3]) / 3
    np.testing.assert_allclose(sets["small_tree_0"].centers.mean(0), [5.0, 0.0, 1.4] + yaw @ local_mean, atol=1e-9)
    np.testing.assert_allclose(np.sort(sets["rock_1"].scales, axis=1), np.tile([0.2, 0.25, 0.325], (2, 1)), rtol=1e-6)
    with pytest.raises(SceneError, match="no 'large_tree'"):
        composed_element_sets(annotation, library, missing="error")


def test_dict_simulates_and_xml_reloads_unchanged(composed, tmp_path):
    _, annotation, library = composed
    sets = composed_element_sets(annotation, PrimitiveLibrary.load(library))
    from_dict = mi_lidar.load_scene(scene_dict(sets))
    from_xml = mi_lidar.load_scene(save_scene(tmp_path / "composed.xml", sets))
    a, b = ElementTable.from_scene(from_dict), ElementTable.from_scene(from_xml)
    assert sorted(a.shape_ids) == sorted(b.shape_ids) == sorted(sets)
    for name in sets:
        ka, kb = a.shape_ids.index(name), b.shape_ids.index(name)
        sa = slice(sum(a.element_counts[:ka]), sum(a.element_counts[: ka + 1]))
        sb = slice(sum(b.element_counts[:kb]), sum(b.element_counts[: kb + 1]))
        for field in ("p_hit", "range_sigma", "label", "kind"):
            np.testing.assert_allclose(np.asarray(getattr(a, field))[sa], np.asarray(getattr(b, field))[sb], rtol=1e-6)
    scans = [mi_lidar.simulate(scene, pattern(300), poses=sensor_pose(), seed=2) for scene in (from_dict, from_xml)]
    labels = scans[0].attributes["label"][scans[0].hit]
    assert {CLASS_ID["ground"], CLASS_ID["small_tree"], CLASS_ID["rock"]} <= set(np.unique(labels))
    np.testing.assert_array_equal(scans[0].hit, scans[1].hit)
    np.testing.assert_allclose(scans[0].ranges, scans[1].ranges, rtol=1e-5, equal_nan=True)


def test_objects_are_calibrated_by_name(composed):
    _, annotation, library = composed
    truth = composed_element_sets(annotation, library)
    truth["small_tree_0"].p_hit = np.full(3, 0.7)
    model = SensorModel(range_sigma=0.02)
    poses = np.stack([sensor_pose()] * 4)
    poses[:, 0, 3] = [0.0, 0.5, 1.0, 1.5]
    log = mi_lidar.simulate(mi_lidar.load_scene(scene_dict(truth)), pattern(800), poses=poses, seed=3, model=model)
    start = composed_element_sets(annotation, library)  # the library's 0.4
    cal = Calibration(
        mi_lidar.load_scene(scene_dict(start)),
        log,
        ["elements.small_tree_0.p_hit"],
        model=model,
        options=FitOptions(steps=30, batch_size=1 << 14, eval_every=5, seed=1),
    )
    assert {"elements.rock_1.centers", "elements.small_tree_2.p_hit"} <= set(cal.space.params)
    result = cal.fit()
    seen = result.observations["elements.small_tree_0.p_hit"] >= 300  # binomial std <= 0.027
    assert seen.sum() >= 2
    assert np.abs(result.fitted["elements.small_tree_0.p_hit"] - 0.7)[seen].max() < 0.08
    assert result.fitted_nll < result.initial_nll


def test_loose_ellipsoids_form_one_set():
    model_sets = hybrid_element_sets(
        mi_lidar.hybrid.model.HybridModel(
            GroundMesh(np.zeros((0, 3)), np.zeros((0, 3))),
            EllipsoidSet(np.zeros((2, 3)), np.tile(np.eye(3) * 0.01, (2, 1, 1)), label=5),
        )
    )
    assert list(model_sets) == ["ellipsoids"] and len(model_sets["ellipsoids"].centers) == 2
