"""3D scan matching on a known room: the registration recovers the true pose from perturbed starts."""

import numpy as np
import pytest

from mi_lidar.apps.matching3d import FrameStates, ScanMatching3D, perturbations, pose_error, rotation
from mi_lidar.core.errors import ParameterError

ROOM = (np.array([-10.0, -7.0, -1.5]), np.array([10.0, 7.0, 2.5]))  # walls, floor and ceiling (m)
BOXES = [  # obstacles: (low corner, high corner), m
    (np.array([3.0, 1.0, -1.5]), np.array([4.0, 2.5, 2.5])),
    (np.array([-6.0, -4.0, -1.5]), np.array([-4.5, -3.5, 0.5])),
    (np.array([-2.0, 4.0, -1.5]), np.array([1.0, 5.0, 1.0])),
]


def spinning_rays(beams: int = 16, columns: int = 512) -> np.ndarray:
    """(beams x columns, 3) unit directions of a spinning sensor, elevations -15 to +15 deg."""
    elevation = np.radians(np.linspace(-15, 15, beams))[:, None]
    azimuth = np.linspace(0, 2 * np.pi, columns, endpoint=False)[None, :]
    d = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        -1,
    )
    return d.reshape(-1, 3)


def cast(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Range (m) to the first surface of the room and its boxes along each ray (slab tests)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / directions
        t1, t2 = (ROOM[0] - origin) * inv, (ROOM[1] - origin) * inv
        r = np.nanmin(np.maximum(t1, t2), axis=1)  # leaving the room
        for lo, hi in BOXES:
            a, b = (lo - origin) * inv, (hi - origin) * inv
            near, far = np.nanmax(np.minimum(a, b), axis=1), np.nanmin(np.maximum(a, b), axis=1)
            entering = (near <= far) & (near > 0)
            r = np.where(entering & (near < r), near, r)
    return r


def room_states(starts: int = 6) -> tuple[FrameStates, np.ndarray]:
    """A map of the room (denser scans from three other places) and the scan's rays at (0.5, -0.5, 0)."""
    map_points = []
    for place in ([-5.0, 2.0, 0.0], [6.0, -3.0, 0.3], [0.0, 0.0, 0.5]):
        d = spinning_rays(32, 1024)
        map_points.append(place + cast(np.array(place), d)[:, None] * d)
    origin = np.array([0.5, -0.5, 0.0])
    d = spinning_rays()
    states = FrameStates(np.concatenate(map_points), np.tile(origin, (len(d), 1)), d, perturbations(starts, seed=3))
    return states, cast(origin, d)[None]


def test_perturbations_are_rigid_seeded_and_of_the_requested_size():
    a, b = perturbations(5, seed=1), perturbations(5, seed=1)
    np.testing.assert_array_equal(a, b)
    for t in a:
        np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)
        assert np.hypot(*t[:2, 3]) == pytest.approx(1.0)
        assert np.degrees(pose_error(t)[1]) <= np.sqrt(5**2 + 2 * 1**2) + 1e-9


def test_pose_error_of_a_known_transform():
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rotation([0, 0, 1], np.radians(3.0)), [0.3, -0.4, 0.0]
    translation, angle = pose_error(t)
    assert translation == pytest.approx(0.5) and np.degrees(angle) == pytest.approx(3.0)


def test_the_scan_of_a_known_room_registers_to_the_true_pose_from_every_start():
    states, ranges = room_states()
    app = ScanMatching3D()
    result = app.evaluate({"max_distance": 2.0, "voxel": 0.2, "method": 2.0, "iterations": 40.0}, states, ranges)
    assert result["failed"] == 0.0
    assert result["translation"] < 0.02 and result["rotation_deg"] < 0.1  # GICP on noise-free planes
    assert len(result["J_starts"]) == 6 and result["J"] == pytest.approx(np.mean(result["J_starts"]))


def test_a_short_correspondence_distance_fails_from_a_metre_away():
    states, ranges = room_states()
    app = ScanMatching3D()
    good = {"max_distance": 2.0, "voxel": 0.2, "method": 1.0, "iterations": 40.0}
    short = app.evaluate({**good, "max_distance": 0.25}, states, ranges)
    assert short["failed"] > 0.5  # a 1 m start error leaves no correspondence within 25 cm on most surfaces
    assert (
        app.evaluate(good, states, ranges)["failed"] == 0.0
        and short["J"] > 10 * app.evaluate(good, states, ranges)["J"]
    )


def test_a_scan_without_returns_is_a_clear_error():
    states, ranges = room_states()
    with pytest.raises(ParameterError, match="needs at least 10"):
        ScanMatching3D().evaluate(
            {"max_distance": 1.0, "voxel": 0.2, "method": 2.0, "iterations": 5.0}, states, ranges * np.nan
        )
