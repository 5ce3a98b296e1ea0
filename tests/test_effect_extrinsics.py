"""extrinsics: the sensor pose offset moves ray origins and turns directions where geometry says.

A sensor 2 m above an opaque floor faces a wall 10 m ahead; without noise every simulated range
must equal the analytic range from the offset origin ``p + t`` along ``exp([r]x) d`` (within
1e-4 relative, float32 tracing).
"""

import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mi_lidar.core.effects.extrinsics import rotate_vector

from .calibration.scenes import SCAN_HEIGHT, analytic_ranges, floor_and_wall_scan, pattern, unit_directions


@pytest.mark.parametrize(
    "rotation,translation",
    [((0, 0, 0), (0.3, -0.2, 0.5)), ((0.0, 0.02, -0.03), (0, 0, 0)), ((0.01, -0.015, 0.02), (-0.4, 0.1, 0.25))],
)
def test_pose_offset_moves_hits_where_geometry_says(rotation, translation):
    names = dict(zip(("rx", "ry", "rz", "tx", "ty", "tz"), (*rotation, *translation)))
    effect = "extrinsics(" + ", ".join(f"{k}={v}" for k, v in names.items()) + ")"
    yaw = 0.4  # rad: the offsets act in the sensor frame, not the world's
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0, 0, yaw]).as_matrix()
    pose[2, 3] = SCAN_HEIGHT
    p = pattern(360)
    ranges, hit = floor_and_wall_scan(effect, seed=0, range_sigma=0.0, firings=360, pose=pose)
    rotation_matrix = pose[:3, :3] @ Rotation.from_rotvec(rotation).as_matrix()
    directions = unit_directions(p.elevation, p.azimuth) @ rotation_matrix.T
    origin = pose[:3, 3] + pose[:3, :3] @ np.asarray(translation, float)
    expected = analytic_ranges(origin, directions)
    finite = np.isfinite(expected) & (expected < 100)
    assert finite.sum() > 2000 and hit[finite].all()
    np.testing.assert_allclose(ranges[finite], expected[finite], rtol=1e-4)


def test_rotation_vector_matches_rodrigues():
    omega = np.array([0.3, -0.2, 0.1])
    v = np.array([0.2, 0.5, -0.8])
    turned = rotate_vector(mi.Vector3f(*map(float, omega)), mi.Vector3f(*map(float, v)))
    np.testing.assert_allclose(
        np.array([turned.x[0], turned.y[0], turned.z[0]]), Rotation.from_rotvec(omega).apply(v), atol=1e-6
    )
    at_zero = rotate_vector(mi.Vector3f(0, 0, 0), mi.Vector3f(*map(float, v)))
    np.testing.assert_allclose(np.array([at_zero.x[0], at_zero.y[0], at_zero.z[0]]), v, atol=1e-7)
