"""KITTI's ``occluded`` from the reference camera: hidden fractions of boxes behind other objects."""

import math

import mitsuba as mi
import numpy as np
import pytest

import mi_lidar  # noqa: F401  (variant and plugins)
from mi_lidar.dataset.occlusion import hidden_fractions, occlusion_level
from mi_lidar.dataset.scenes import Box3D, instance_by_registry
from mi_lidar.scene.camera import PinholeCamera


def cube(center, half):
    transform = mi.ScalarTransform4f().translate(list(map(float, center))).scale(list(map(float, half)))
    return {"type": "cube", "to_world": transform}


def box(instance, center, half):
    return Box3D("Car", instance, np.asarray(center, float), 2 * np.asarray(half, float), 0.0)


@pytest.mark.parametrize("wall_y, expected", [(None, 0.0), (0.0, 0.5), (-0.5, 0.75), (-1.5, 1.0)])
def test_a_wall_in_front_hides_the_expected_share_of_a_box(wall_y, expected):
    """The camera at the origin looks along +x at a 2 m cube 10 m away (instance 1, front face at x = 9 m).
    A wall at x = 5 m whose right edge lines up with y = wall_y on that face hides the face's part left of
    it; the 16 x 16 ray grid spans the face's 2D box, so the hidden fraction is the covered share of the
    face, exact when the edge falls on a boundary between grid columns (0, -0.5 m; -1.5 m hides it all)."""
    shapes = {"type": "scene", "target": cube([10, 0, 0], [1, 1, 1]), "floor": cube([10, 0, -3], [30, 30, 0.5])}
    if wall_y is not None:
        edge = wall_y * 5 / 9  # the wall's right edge at x = 5 m shadows y = wall_y at the front face
        shapes["wall"] = cube([5, edge + 5, 0], [0.05, 5, 5])
    scene = mi.load_dict(shapes)
    registry = instance_by_registry(scene, {"target": 1})
    camera = PinholeCamera.look_at([0, 0, 0], [1, 0, 0], width=400, height=300, fov_deg=60)
    hidden = hidden_fractions(scene, camera, [box(1, [10, 0, 0], [1, 1, 1])], registry)
    assert hidden[1] == pytest.approx(expected, abs=1e-9)
    assert occlusion_level(hidden[1]) == {0.0: 0, 0.5: 1, 0.75: 2, 1.0: 2}[expected]


def test_boxes_out_of_view_are_left_out_and_a_missed_object_is_unknown():
    """A box behind the camera gets no entry; a box whose object no grid ray meets is unknown (3)."""
    scene = mi.load_dict(
        {"type": "scene", "pole": cube([10, 0, 0], [0.001, 0.001, 1]), "back": cube([-10, 0, 0], [1, 1, 1])}
    )
    registry = instance_by_registry(scene, {"pole": 1, "back": 2})
    camera = PinholeCamera.look_at([0, 0, 0], [1, 0, 0], width=400, height=300, fov_deg=60)
    boxes = [box(1, [10, 0, 0], [0.5, 0.5, 1]), box(2, [-10, 0, 0], [1, 1, 1])]
    hidden = hidden_fractions(scene, camera, boxes, registry)
    assert list(hidden) == [1] and math.isnan(hidden[1])
    assert occlusion_level(hidden[1]) == 3
