"""The planar applications on the test room, where the answer is known (tests/apps/room.py)."""

from types import SimpleNamespace

import numpy as np
import pytest

from mi_lidar.apps.lines import LineDetection, match_segments, split_and_merge
from mi_lidar.apps.localization import ParticleFilter, distance_field, low_variance_resample
from mi_lidar.apps.registration import MapIndex, ScanToMapEKF, icp
from mi_lidar.apps.scans import (
    compose,
    noisy_runs,
    paired_runs,
    relative,
    scan_points,
    stretches,
    to_world,
    wrap,
)
from mi_lidar.apps.walls import map_walls, visible_walls
from tests.apps.room import GRID, cast_scans, room_ranges, room_states, wall_cells
from tests.planar.world import WALLS


@pytest.fixture(scope="module")
def room():
    return room_states(scans=30)


def test_poses_compose_and_invert():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    assert np.allclose(compose(a, relative(a, b)), b)
    points = rng.normal(size=(4, 2))
    # A point of frame b seen from the world equals the same point seen through a then a^-1 b.
    inner = to_world(relative(a[0], b[0]), points)
    assert np.allclose(to_world(b[0], points), to_world(a[0], inner))


def test_icp_registers_a_room_scan_to_the_true_pose(room):
    ranges = room_ranges(room, sigma=0.02)
    index = MapIndex.build(room.maps.points(0))
    for t in (0, 7, 19):
        start = room.poses[t] + np.array([0.3, -0.25, np.radians(6.0)])
        result = icp(scan_points(ranges[t], room.angles), index, start, 1.0, 30)
        pose = result.pose
        # 2 cm noise on ~180 points: the pose is found to well under a centimetre and a tenth of a degree.
        assert np.hypot(*(pose[:2] - room.poses[t, :2])) < 0.01, (t, pose, room.poses[t])
        assert abs(wrap(pose[2] - room.poses[t, 2])) < np.radians(0.1)
        assert result.share > 0.95 and result.iterations < 30


def test_ekf_tracks_the_room_and_unmapped_clutter_needs_a_tight_inlier_distance(room):
    app = ScanToMapEKF(runs=2)
    tight = {"max_distance": 0.5, "iterations": 12.0, "min_inliers": 0.4}
    loose = {"max_distance": 1.2, "iterations": 1.0, "min_inliers": 0.0}
    clean = app.evaluate(tight, room, room_ranges(room, sigma=0.02))
    assert clean["J"] < 0.03 and clean["rejected"] == 0.0, clean
    clutter = room_ranges(room, sigma=0.02, short=0.25)
    # A quarter of the returns short of the walls: one ICP step with far pairs is pulled off (measured 0.12 vs 0.024 m).
    assert app.evaluate(loose, room, clutter)["J"] > 3 * app.evaluate(tight, room, clutter)["J"]


def test_particle_filter_localizes_in_the_room(room):
    app = ParticleFilter(runs=2)
    ranges = room_ranges(room, sigma=0.02)
    good = app.evaluate({"particles": 400.0, "sigma_hit": 0.1, "z_rand": 0.05}, room, ranges)
    assert good["J"] < 0.08 and good["divergence"] == 0.0, good
    # 50 particles with a 1 cm likelihood field lose track (measured J 0.36 m on 40 states).
    poor = app.evaluate({"particles": 50.0, "sigma_hit": 0.01, "z_rand": 0.001}, room, ranges)
    assert poor["J"] > 3 * good["J"], (poor, good)


def test_distance_field_and_resampling():
    occupancy = np.zeros((5, 5), bool)
    occupancy[2, 2] = True
    field = distance_field(occupancy, 0.1)[1:-1, 1:-1]  # without the padding
    assert field[2, 2] == 0 and field[2, 4] == 20 and field[0, 0] == round(100 * np.hypot(0.2, 0.2))
    weights = np.array([[0.0, 0.75, 0.25, 0.0], [0.5, 0.0, 0.0, 0.5]])
    picks = low_variance_resample(weights, np.array([0.3, 0.9]))
    assert np.array_equal(np.bincount(picks[0], minlength=4), [0, 3, 1, 0])
    assert np.array_equal(np.bincount(picks[1], minlength=4), [2, 0, 0, 2])


def test_stretches_cut_the_log_by_travel():
    straight = SimpleNamespace(n=20, poses=np.c_[np.arange(20.0), np.zeros(20), np.zeros(20)])  # 1 m apart
    assert stretches(straight, 5.0) == [(0, 6), (6, 12), (12, 18), (18, 20)]
    assert stretches(straight, 100.0) == [(0, 20)]
    # A cap on the states keeps evenly spaced whole stretches.
    assert stretches(straight, 5.0, max_states=12) == [(0, 6), (18, 20)]


def test_paired_runs_add_runs_while_the_objective_is_uncertain():
    def batch(indices):
        return {"objective": (indices % 2).astype(float), "index": indices}

    coin = paired_runs(batch, runs=4, max_runs=12, target_se=0.01)  # 0, 1, 0, 1, ...: SE 0.15 after 12 runs
    assert np.array_equal(coin["index"], np.arange(12))
    steady = paired_runs(lambda i: {"objective": np.full(i.size, 0.3)}, runs=4, max_runs=12, target_se=0.01)
    assert steady["objective"].size == 4


def test_runs_share_their_noise_whatever_the_number_of_runs(room):
    two, four = noisy_runs(room, 2, seed=5), noisy_runs(room, 4, seed=5)
    assert np.array_equal(two[0], four[0][:2]) and np.array_equal(two[1], four[1][:2])
    assert not np.allclose(four[1][0], four[1][1])


def test_walls_of_the_room_map_are_its_walls():
    occupancy = np.zeros(GRID.size, bool)
    occupancy[wall_cells()] = True
    found = map_walls(occupancy.reshape(GRID.shape), GRID)
    # Every wall of the room is found once, on its line within 3 cm and 2 deg, covering all but its corners.
    assert len(found) == len(WALLS), found
    for wall in WALLS:
        direction = (wall[2:] - wall[:2]) / np.hypot(*(wall[2:] - wall[:2]))
        rel = found.reshape(-1, 2, 2) - wall[:2]
        offset = np.abs(rel[..., 0] * direction[1] - rel[..., 1] * direction[0]).max(axis=1)
        k = int(np.argmin(offset))
        assert offset[k] < 0.03, (wall, found[k])
        along = np.sort(rel[k] @ direction)
        assert along[0] < 0.25 and along[1] > np.hypot(*(wall[2:] - wall[:2])) - 0.25, (wall, found[k])


def test_visible_walls_are_the_walls_the_nominal_scan_sees(room):
    pose = room.poses[5]
    pieces = visible_walls(WALLS, pose, room.nominal[5], room.angles, min_beams=5)
    per_wall = np.stack([cast_scans(pose[None], room.angles, WALLS[k : k + 1])[0] for k in range(len(WALLS))])
    nearest = np.argmin(per_wall, axis=0)
    runs = np.flatnonzero(np.diff(np.concatenate([[-1], nearest, [-1]])) != 0)
    expected = sum(1 for a, b in zip(runs[:-1], runs[1:]) if b - a >= 5 and np.isfinite(per_wall[nearest[a], a]))
    assert len(pieces) == expected >= 3
    # Each piece lies on a wall of the room.
    for x0, y0, x1, y1 in pieces:
        rel = np.array([[x0, y0], [x1, y1]])[:, None, :] - WALLS[None, :, :2]
        d = WALLS[:, 2:] - WALLS[:, :2]
        d = d / np.hypot(d[:, 0], d[:, 1])[:, None]
        assert np.min(np.abs(rel[..., 0] * d[:, 1] - rel[..., 1] * d[:, 0]).max(axis=0)) < 1e-6


def test_split_and_merge_finds_the_visible_walls_of_the_room(room):
    pose = room.poses[5:6]
    per_wall = np.stack([cast_scans(pose, room.angles, WALLS[k : k + 1])[0] for k in range(len(WALLS))])  # (W, N)
    ranges = per_wall.min(axis=0) + np.random.default_rng(3).normal(0.0, 0.01, room.angles.size)
    found = split_and_merge(scan_points(ranges, room.angles), 0.1, 8, 0.3)
    # The walls that at least 8 beams see, in the laser frame.
    visible = np.flatnonzero(np.bincount(np.argmin(per_wall, axis=0), minlength=len(WALLS)) >= 8)
    ends = [relative(pose[0], np.c_[WALLS[visible, k : k + 2], np.zeros(visible.size)])[:, :2] for k in (0, 2)]
    assert len(visible) >= 3 and len(found) == len(visible), (found, visible)
    assert match_segments(found, np.concatenate(ends, axis=1)) == len(visible)


def test_line_detection_is_perfect_on_the_maps_own_walls(room):
    app = LineDetection()
    # On the nominal scans a detector that keeps 5 points finds the visible wall pieces (5 beams or more each); the
    # only disagreements are two 5-point pieces behind a corner whose corner beam the reference gives the other wall.
    exact = app.evaluate({"split": 0.05, "min_points": 5.0, "gap": 2.0}, room, room.nominal)
    assert exact["J"] < 0.01 and exact["recall"] == 1.0, exact
    noisy = room_ranges(room, sigma=0.02, short=0.2)
    assert app.evaluate({"split": 0.01, "min_points": 3.0, "gap": 2.0}, room, noisy)["J"] > 0.5
