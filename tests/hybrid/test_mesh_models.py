"""The thesis's mesh-model baseline: stock generator models per class, chosen by closest box, placed unscaled."""

import numpy as np
import pytest

from mi_lidar.core.errors import SceneError
from mi_lidar.hybrid.baselines import box_surface_scene, mesh_model_scene
from mi_lidar.hybrid.classes import CLASS_ID, OBJECT_CLASSES
from mi_lidar.hybrid.compose import annotation_from_segments
from mi_lidar.hybrid.fit import world_rays
from mi_lidar.hybrid.mesh_models import MeshModelLibrary
from mi_lidar.hybrid.primitives import rotation_z
from mi_lidar.hybrid.segments import segments_from_labels
from mi_lidar.hybrid.simulation import simulate_log
from mi_lidar.hybrid.world import CLASS_SHAPES


@pytest.fixture(scope="module")
def library():
    return MeshModelLibrary.generate(per_class=3)


@pytest.fixture(scope="module")
def annotation(small_log, small_fit):
    labels = small_log.attributes["label"].ravel()[small_fit.ray_index]
    inst = small_log.attributes["instance"].ravel()[small_fit.ray_index]
    return annotation_from_segments(
        small_fit.points, segments_from_labels(small_fit.points, labels, inst), small_log.poses
    )


def _area_centroid_above(vertices, faces, base_z):
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    centroid = tri.mean(axis=1)
    above = centroid[:, 2] > base_z
    return np.average(centroid[above], axis=0, weights=area[above])


def test_library_has_every_object_class_in_growing_sizes_within_the_class_range(library):
    assert len(library) == 3 * len(OBJECT_CLASSES)
    for label in OBJECT_CLASSES:
        models = [m for m in library.models if m.label == label]
        assert len(models) == 3
        assert np.all(np.diff([m.size for m in models]) > 0)
        if label != CLASS_ID["rock"]:
            lo, hi = CLASS_SHAPES[models[0].id.rsplit("_", 1)[0]][0]
            heights = np.array([m.extents[2] for m in models])
            assert np.all(heights > 0.9 * lo) and np.all(heights < 1.1 * hi)


def test_model_frame_origin_is_the_surface_centroid_above_the_base(library):
    for m in library.models:
        base = m.vertices[:, 2].max() - m.extents[2]  # the box bottom is the base plane
        assert np.allclose(_area_centroid_above(m.vertices, m.faces, base), 0.0, atol=1e-6)


def test_models_of_a_class_differ_and_repeat_for_a_seed(library):
    a, b = [m for m in library.models if m.label == CLASS_ID["medium_tree"]][:2]
    assert len(a.faces) != len(b.faces) or not np.allclose(a.vertices[:50], b.vertices[:50])
    again = MeshModelLibrary.generate(per_class=3)
    np.testing.assert_array_equal(again.models[5].vertices, library.models[5].vertices)
    other = MeshModelLibrary.generate(per_class=3, seed=1)
    assert not np.array_equal(other.models[5].vertices, library.models[5].vertices)


def test_best_match_is_the_closest_box_of_the_same_class(library):
    shrubs = [m for m in library.models if m.label == CLASS_ID["small_shrub"]]
    for target in shrubs:
        assert library.best_match("small_shrub", target.extents + 0.05).id == target.id
    # a box shaped like a large tree still gets a small shrub: the class decides, then the box
    tree = [m for m in library.models if m.label == CLASS_ID["large_tree"]][-1]
    chosen = library.best_match("small_shrub", tree.extents)
    assert chosen.label == CLASS_ID["small_shrub"]
    assert chosen.id == min(shrubs, key=lambda m: np.linalg.norm(m.extents - tree.extents)).id
    with pytest.raises(SceneError, match="no 'rock'"):
        MeshModelLibrary(shrubs).best_match("rock", [1, 1, 1])


def test_placed_model_sits_at_the_object_pose_unscaled(library):
    model = [m for m in library.models if m.label == CLASS_ID["medium_tree"]][1]
    center, yaw = np.array([12.0, -3.0, 5.0]), 0.7
    for extents in (model.extents, 1.05 * model.extents):  # a 5 % larger box: same model, same size
        obj = {"class": "medium_tree", "center": center.tolist(), "yaw": yaw, "extents": extents.tolist()}
        scene = mesh_model_scene([obj], None, library)
        assert scene.info["models"] == [model.id]
        placed = scene.ground.vertices[np.unique(scene.ground.faces[scene.ground.instance == 1])]
        np.testing.assert_allclose((placed - center) @ rotation_z(yaw), model.vertices, atol=1e-9)


def test_mesh_model_scene_is_opaque_and_returns_from_the_models(small_log, small_fit, annotation, library):
    base = mesh_model_scene(annotation, small_fit.model.ground, library, sigma=0.05)
    assert np.all(base.ground.p_hit == 1) and np.allclose(base.ground.range_sigma, 0.05)
    assert len(base.ellipsoids) == 0 and len(base.info["models"]) == len(annotation)
    r1, label1 = simulate_log(base, small_log, seed=1)
    r2, label2 = simulate_log(base, small_log, seed=2)
    # opaque: which rays return, and from what, does not depend on the seed; only the range noise does
    np.testing.assert_array_equal(np.isfinite(r1), np.isfinite(r2))
    np.testing.assert_array_equal(label1, label2)
    diff = (r1 - r2)[np.isfinite(r1)]
    assert 0.04 < np.std(diff) / np.sqrt(2) < 0.06
    on_object = np.isin(label1, OBJECT_CLASSES)
    assert on_object.sum() > 500
    # returns labelled with an object class lie on placed models (inside their bounding boxes)
    origins, directions = world_rays(small_log)
    points = (origins + r1.reshape(-1, 1) * directions)[on_object.ravel()]
    models = base.ground.subset(base.ground.instance > 0)
    lo, hi = models.vertices[models.faces].min(axis=(0, 1)), models.vertices[models.faces].max(axis=(0, 1))
    assert np.all((points >= lo - 0.3) & (points <= hi + 0.3))


def test_box_surface_scene_scales_each_surface_to_its_box(annotation, small_fit):
    base = box_surface_scene(annotation, small_fit.model.ground, sigma=0.05)
    assert np.all(base.ground.p_hit == 1) and len(base.ellipsoids) == 0
    for i in (0, len(annotation) - 1):
        obj = annotation[i]
        placed = base.ground.vertices[np.unique(base.ground.faces[base.ground.instance == i + 1])]
        local = (placed - np.asarray(obj["center"])) @ rotation_z(obj["yaw"])
        np.testing.assert_allclose(np.ptp(local, axis=0), np.maximum(obj["extents"], 0.1), rtol=0.02)
