"""fit-scene on a planar log: the log's permeable wall map as a Mitsuba scene (mi_lidar.planar.map_scene).

The room of tests/planar/world.py: walls at x = 0, 12 and y = 0, 8, a 1 m pillar, and a glass pane at x = 3
(y 6-8) that stops a beam with probability 0.3, scanned from 200 poses on an ellipse (1 cm range noise).
"""

import re

import mitsuba as mi
import numpy as np
import pytest
from plyfile import PlyData

import mi_lidar
from mi_lidar.core.errors import LogFormatError
from mi_lidar.io.carmen import beam_angles
from mi_lidar.io.dispatch import read_any
from mi_lidar.planar.grid import Grid
from mi_lidar.planar.map_scene import fit_map_scene
from mi_lidar.planar.wall_map import CELL, HALF_HEIGHT, WallMap, face_p_hit, surface_ends, wall_faces
from tests.io.test_clouds import synthetic_log
from tests.planar.world import GLASS, WALLS, cast, flaser_text, room_log_text, room_readings
from tests.planar.world import poses as room_poses
from tests.terminal import invoke_at_80

GLASS_P = 0.3


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The room's CARMEN log, read, and its wall map written (scene.xml, walls.ply, pattern.npy)."""
    folder = tmp_path_factory.mktemp("room")
    (folder / "room.log").write_text(room_log_text(scans=200, sigma=0.01, glass_p=GLASS_P, seed=4))
    log = read_any(folder / "room.log")
    xml, mesh, pattern = fit_map_scene(log, folder / "map", preview=False)
    return log, xml, mesh, pattern


def segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(P,) distance (m) of (P, 2) points to the nearest of (M, 4) segments."""
    a, ab = segments[:, :2], segments[:, 2:] - segments[:, :2]
    t = np.clip(np.einsum("pmk,mk->pm", points[:, None] - a[None], ab) / (ab**2).sum(axis=1), 0.0, 1.0)
    return np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1).min(axis=1)


def boxes(grid: Grid, cells, hits, passes, plane_z: float) -> WallMap:
    """A wall map of boxes only."""
    n = len(cells)
    return WallMap(
        grid, np.array(cells), np.array(hits), np.array(passes), plane_z, np.zeros(n, bool), np.full((n, 2, 2), np.nan)
    )


def test_two_faces_stop_a_beam_with_the_cell_probability():
    """A beam crosses two side faces of a box: each face's q = 1 - sqrt(1 - p) so that 1 - (1 - q)^2 = p; a face
    between two boxes is written once, stopping with 1 - (1 - q_1)(1 - q_2)."""
    p = np.array([0.0, 0.3, 0.9, 0.999])
    np.testing.assert_allclose(1 - (1 - face_p_hit(p)) ** 2, p, atol=1e-12)
    grid = Grid(origin=(0.0, 0.0), cell=0.1, shape=(4, 4))
    one = boxes(grid, [5], [3], [7], plane_z=0.5)  # cell (1, 1), p = 4 / 11.1
    vertices, triangles, q = wall_faces(one)
    assert len(triangles) == 8 and np.allclose(q, face_p_hit(4 / 11.1))  # four side faces, two triangles each
    assert np.allclose(vertices.min(axis=0), [0.1, 0.1, 0.5 - HALF_HEIGHT])
    assert np.allclose(vertices.max(axis=0), [0.2, 0.2, 0.5 + HALF_HEIGHT])
    two = boxes(grid, [5, 9], [3, 1], [7, 0], plane_z=0.0)  # cells (1, 1), (2, 1)
    vertices, triangles, q = wall_faces(two)
    shared = np.isclose(vertices[triangles][..., 0], 0.2).all(axis=1)  # the face at x = 0.2 between them
    assert len(triangles) == 14 and shared.sum() == 2
    q1, q2 = face_p_hit(4 / 11.1), face_p_hit(2 / 2.1)
    np.testing.assert_allclose(q[shared], 1 - (1 - q1) * (1 - q2), rtol=1e-6)


def test_the_surfaces_of_neighbouring_cells_join_on_their_common_edge():
    """Two cells side by side whose hits lie on lines y = 0.14 and 0.16 m: each surface is its line clipped to its
    cell, and both end at y = 0.15 on the edge x = 0.2 between them; a surface is one quad stopping a beam with p."""
    grid = Grid(origin=(0.0, 0.0), cell=0.1, shape=(4, 4))
    ends = surface_ends(grid, np.array([5, 9]), np.array([[0.05, 0.04], [0.05, 0.06]]), np.array([[0.0, 1.0]] * 2))
    np.testing.assert_allclose(np.sort(ends[0], axis=0), [[0.1, 0.14], [0.2, 0.15]], atol=1e-12)
    np.testing.assert_allclose(np.sort(ends[1], axis=0), [[0.2, 0.15], [0.3, 0.16]], atol=1e-12)
    walls = WallMap(grid, np.array([5, 9]), np.array([3, 1]), np.array([7, 0]), 0.0, np.ones(2, bool), ends)
    vertices, triangles, p = wall_faces(walls)
    assert len(triangles) == 4 and len(vertices) == 6  # two quads sharing the vertical edge at (0.2, 0.15)
    np.testing.assert_allclose(np.sort(p), np.sort(np.repeat([4 / 11.1, 2 / 2.1], 2)))


def test_a_wall_between_cell_edges_is_mapped_where_its_returns_are(tmp_path):
    """A straight wall at x = 3.023 m, 2.3 cm inside its 5 cm cell (the grid's cells start 1 m before the first
    pose, at x = 0): the map stopped the beams at the cell's edge, x = 3.00 m, 2.3 cm in front of the wall; now its
    surfaces lie where the returns are. Traced through the map's faces (each stopping a beam with its p_hit), the
    beams that meet the wall at under 60 deg of incidence from the 40 poses stop a mean 0.5 mm in front of the wall
    (tolerance 5 mm; the cell boxes: 18.3 mm), and each stops within 5 cm of it with probability 0.85 at least (no
    gaps between the surfaces; 0.91 at worst, where 3 of the 34 returns lay 3 cm behind the wall)."""
    rng = np.random.default_rng(7)
    wall = np.array([[3.023, -4.0, 3.023, 4.0]])
    poses = np.stack([np.linspace(0.0, 2.0, 40), rng.uniform(-2.0, 2.0, 40), rng.uniform(-0.5, 0.5, 40)], axis=1)
    angles = poses[:, 2:] + beam_angles(181)
    origin = np.broadcast_to(poses[:, None, :2], (40, 181, 2)).reshape(-1, 2)
    direction = np.stack([np.cos(angles), np.sin(angles)], axis=-1).reshape(-1, 2)
    truth = cast(origin, direction, wall)[:, 0]
    readings = np.where(np.isfinite(truth), truth + rng.normal(0.0, 0.01, truth.size), 50.0).reshape(40, 181)
    (tmp_path / "wall.log").write_text(flaser_text(poses, readings, "a wall at x = 3.023 m"))
    _, mesh, _ = fit_map_scene(read_any(tmp_path / "wall.log"), tmp_path / "map", preview=False)
    ply = PlyData.read(str(mesh))
    xy = np.stack([ply["vertex"]["x"], ply["vertex"]["y"]], axis=1)
    triangles = np.stack(ply["face"]["vertex_indices"])
    lower = slice(0, len(triangles) // 2)  # the first triangle of each vertical face spans its two ends
    faces = np.concatenate([xy[triangles[lower, 0]], xy[triangles[lower, 1]]], axis=1)
    p = np.asarray(ply["face"]["p_hit_0"])[lower]
    steep = np.isfinite(truth) & (np.abs(direction[:, 0]) > np.cos(np.radians(60)))
    met = cast(origin[steep], direction[steep], faces)  # (B, F) range to each face, inf where missed
    order = np.argsort(met, axis=1)
    t, q = np.take_along_axis(met, order, 1), np.where(np.isfinite(np.take_along_axis(met, order, 1)), p[order], 0.0)
    stop = q * np.cumprod(np.c_[np.ones(len(q)), 1 - q[:, :-1]], axis=1)  # P(the beam stops at each face)
    x = origin[steep, :1] + np.nan_to_num(t, posinf=0.0) * direction[steep, :1]
    assert steep.sum() > 1000
    assert abs((stop * x).sum() / stop.sum() - 3.023) < 0.005
    assert (stop * (np.abs(x - 3.023) < 0.05)).sum(axis=1).min() > 0.85


def test_the_map_loads_in_mitsuba_and_its_walls_are_where_the_room_is(room):
    log, xml, mesh, pattern = room
    scene = mi.load_file(str(xml))  # the lidar plugins are registered by importing mi_lidar
    (shape,) = scene.shapes()
    assert shape.has_attribute("face_p_hit") and xml.parent / "scene_assets" / "walls.ply" == mesh
    assert mi.traverse(scene.sensors()[0])  # the log's sensor loads with it
    drive = mi_lidar.simulate(mi_lidar.load_scene(xml), poses=log.poses[::10], seed=1)
    hit = drive.hit[..., 0]
    assert hit.mean() > 0.99  # a closed room: every beam returns (99.6 %: the walls' surfaces stop 0.995-0.997)
    nominal = drive.attributes["nominal_range"][..., 0]
    origin = drive.poses[:, None, :2, 3]
    direction = np.einsum("sij,nj->sni", drive.poses[:, :2, :2], log.directions[0, :, 0, :2])
    points = (origin + nominal[..., None] * direction)[hit]
    distance = segment_distance(points, np.concatenate([WALLS, GLASS]))
    # the walls' surfaces lie on them (median 0.8 mm, 99th percentile 2.5 cm here: corners and the pillar are boxes,
    # a face of which is at most a cell diagonal from the wall; with boxes everywhere the median was 1.8 cm)
    assert np.median(distance) < 0.005 and np.percentile(distance, 99) < CELL * np.sqrt(2)


def test_the_glass_stops_the_share_of_beams_it_stopped_in_the_log(room):
    """The pane stops a beam with probability 0.3 (685 of the 2,282 beams that crossed it in front of a wall in this
    log, 30.0 %); the beams the map's faces stop there, over 5 draws at the log's poses, are within 0.05 of 0.3:
    31.2 %. (The pane's surfaces count the log's beams traced through them. Cell boxes stopped 33.9 %: a beam's
    pass-throughs of the cells are counted to a cell short of its return, so the cell in front of the one a return
    ends in misses some of its passes.)"""
    log, xml, *_ = room
    scene = mi_lidar.load_scene(xml)
    stopped = crossed = 0
    for seed in range(5):
        drive = mi_lidar.simulate(scene, poses=log.poses, seed=seed)
        for s, (x, y, heading) in enumerate(room_poses(log.shape[0])):
            angle = heading + np.arctan2(log.directions[0, :, 0, 1], log.directions[0, :, 0, 0])
            direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
            origin = np.repeat([[x, y]], len(angle), axis=0)
            glass = cast(origin, direction, GLASS)[:, 0]
            crosses = glass < cast(origin, direction, WALLS).min(axis=1) - 0.2  # the pane in front of a wall
            nominal = drive.attributes["nominal_range"][s, :, 0]
            crossed += crosses.sum()
            stopped += (crosses & drive.hit[s, :, 0] & (np.abs(nominal - glass) < 2 * CELL)).sum()
    assert crossed > 10_000
    assert stopped / crossed == pytest.approx(GLASS_P, abs=0.05)


def test_fit_scene_builds_the_wall_map_of_a_planar_log_and_compare_scores_it(room, tmp_path):
    """fit-scene on a planar CARMEN log fitted a hybrid 'ground' and warned that the scene was a guess outside the
    plane; it writes the wall map, which compare scores on the log it was built from."""
    log_path = tmp_path / "room.log"
    log_path.write_text(room_log_text(scans=40, sigma=0.01))
    result = invoke_at_80(["fit-scene", log_path, "--out", tmp_path / "map", "--cell", "0.1"])
    said = " ".join(result.output.split())
    assert result.exit_code == 0, result.output
    assert "wall map" in said and "is a planar log" not in said
    assert (tmp_path / "map" / "scene_assets" / "walls.ply").is_file()
    faces = PlyData.read(str(tmp_path / "map" / "scene_assets" / "walls.ply"))["face"].data
    assert 0 < np.asarray(faces["p_hit_0"]).min() and np.asarray(faces["p_hit_0"]).max() < 1
    result = invoke_at_80(["compare", log_path, tmp_path / "map" / "scene.xml", "--out", tmp_path / "report"])
    said = " ".join(result.output.split())
    assert result.exit_code == 0, result.output
    f1 = float(said.split("hit/miss F1 ")[1].split(";")[0])
    assert f1 > 0.98  # 0.997 (0.991 with cell boxes everywhere, through which grazing beams passed)


def carmen_text(poses=None, readings=None, scans: int = 40) -> str:
    """The room's log with its poses (S, 3) or readings (S, beams) replaced."""
    lines = room_log_text(scans=scans, beams=181).splitlines()[1:]
    out = []
    for s, line in enumerate(lines):
        tokens = line.split()
        n = int(tokens[1])
        if readings is not None:
            tokens[2 : 2 + n] = [f"{r:.3f}" for r in readings[s]]
        if poses is not None:
            tokens[2 + n : 2 + n + 3] = [f"{v:.4f}" for v in poses[s]]
        out.append(" ".join(tokens))
    return "\n".join(out) + "\n"


@pytest.mark.parametrize(
    "text, said",
    [
        (
            carmen_text(poses=np.zeros((40, 3))),
            r"all 40 scans have the same pose \(the identity\), yet a beam's returns differ between scans by a median "
            r"\d\.\d\d m: the scanner moved and the log has no poses, .* Give a log with SLAM-corrected poses",
        ),
        (
            carmen_text(readings=np.zeros((40, 181))),
            r"none of the log's 7,240 readings is a return \(every one is <= 0\), so there are no walls to map",
        ),
    ],
    ids=["no-poses", "no-returns"],
)
def test_a_log_that_cannot_make_a_map_is_one_error_line(tmp_path, text, said):
    """Identity poses for a moving scanner fitted a hybrid scene of the smear; a log without returns failed in
    the hybrid fit. Both are one line naming the fix, and no output folder is left."""
    (tmp_path / "bad.log").write_text(text)
    with pytest.raises(LogFormatError, match=said):
        fit_map_scene(read_any(tmp_path / "bad.log"), tmp_path / "out", preview=False)
    result = invoke_at_80(["fit-scene", tmp_path / "bad.log", "--out", tmp_path / "out"])
    assert result.exit_code == 2 and result.output.startswith("error:"), result.output
    assert re.search(said, " ".join(result.output.split())), result.output
    assert not (tmp_path / "out").exists()


def test_a_scanner_that_stood_still_is_mapped(tmp_path):
    """Every scan at one pose is a log without poses only when its scans disagree: a still scanner's map is built."""
    first = room_readings(1, 181, sigma=0.0, glass_p=0.0, max_range=50.0, seed=0)[0]
    noise = np.random.default_rng(1).normal(0.0, 0.01, (40, 181))
    text = carmen_text(poses=np.tile(room_poses(40)[0], (40, 1)), readings=first + noise)
    (tmp_path / "still.log").write_text(text)
    xml, *_ = fit_map_scene(read_any(tmp_path / "still.log"), tmp_path / "map", preview=False)
    assert xml.is_file()


def test_a_climbing_scanner_is_refused(tmp_path):
    """A planar log whose scans climb leaves the map's boxes (1 m tall around the scan plane)."""
    (tmp_path / "room.log").write_text(room_log_text(scans=20, beams=91))
    log = read_any(tmp_path / "room.log")
    log.poses[::2, 2, 3] = 2.0  # every other scan 2 m higher
    with pytest.raises(LogFormatError, match=r"lie more than 0.5 m above or below the scan plane .* needs a 3D scene"):
        fit_map_scene(log, tmp_path / "out", preview=False)


def test_cell_is_refused_for_a_3d_log(tmp_path):
    path = synthetic_log(scans=2).save(tmp_path / "drive.npz")
    result = invoke_at_80(["fit-scene", path, "--out", tmp_path / "out", "--cell", "0.1"])
    assert result.exit_code == 2 and "--cell 0.1: " in result.output and "is a 3D log" in result.output
    assert not (tmp_path / "out").exists()
