"""Georeferenced inputs (UTM-sized coordinates) give the same scans and scenes as the same job near the origin.

Float32 keeps 0.25 m at a northing of 4,000,000 m: without a local frame every range below would be
off by decimetres. Each test runs one job twice, at the origin and translated by OFFSET, and
compares; an input that cannot be made right must be refused with a message naming the value.
"""

import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import laspy
import mitsuba as mi
import numpy as np
import plyfile
import pytest

import mi_lidar
from mi_lidar.core.errors import PoseError, SceneError
from mi_lidar.core.frames import scene_origin
from mi_lidar.core.problem import score_log
from mi_lidar.core.rays import LogRays
from mi_lidar.dataset.run import run_dataset
from mi_lidar.dataset.spec import load_spec
from mi_lidar.hybrid.commands import fit_scene
from mi_lidar.io import read_any, read_poses, write_any, write_kitti_poses
from mi_lidar.scene import scene_sensor_model
from mi_lidar.scene.camera import PinholeCamera, render_camera
from mi_lidar.scene.files import write_mesh_ply
from mi_lidar.scene.rebase import to_world_matrix

from .conftest import SCENES
from .terminal import invoke_at_80

OFFSET = np.array([500000.0, 4000000.0, 100.0])  # a UTM easting, northing and height, m
RANGE_TOLERANCE = 1e-3  # m: the acceptance bound on ranges; measured at most 1.1e-5 m
ASSETS = (SCENES / "assets").resolve()


def offroad_xml(shift) -> str:
    """The bundled off-road terrain and vegetation with a VLP-16 2 m up, every element placed at ``shift``."""
    x, y, z = (float(v) for v in shift)
    place = f'<transform name="to_world"><translate x="{x!r}" y="{y!r}" z="{z!r}"/></transform>'
    turn = '<rotate z="1" angle="30"/>'
    rock = f'<translate x="{x + 16.0!r}" y="{y + 1.0!r}" z="{z + 0.6!r}"/>'
    return f"""<scene version="3.0.0">
    <integrator type="lidar_integrator"><integer name="max_segments" value="16"/></integrator>
    <emitter type="constant"/>
    <sensor type="lidar"><string name="pattern" value="vlp16"/><float name="max_range" value="100"/>
        <transform name="to_world">{turn}<translate x="{x!r}" y="{y!r}" z="{z + 2.0!r}"/></transform>
    </sensor>
    <shape type="ply" id="terrain"><string name="filename" value="{ASSETS}/offroad_terrain.ply"/>{place}
        <bsdf type="lidar_material"><float name="range_sigma" value="0.03"/><integer name="label" value="1"/></bsdf>
    </shape>
    <shape type="cube" id="rock">
        <transform name="to_world"><scale value="0.6"/>{rock}</transform>
    </shape>
    <shape type="ellipsoids" id="vegetation">
        <string name="filename" value="{ASSETS}/offroad_vegetation.ply"/>{place}
    </shape>
</scene>"""


@pytest.fixture(scope="module")
def scene_files(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("georeferenced")
    near, far = folder / "near.xml", folder / "far.xml"
    near.write_text(offroad_xml(np.zeros(3)))
    far.write_text(offroad_xml(OFFSET))
    return near, far


def drive_poses() -> np.ndarray:
    """Three VLP-16 poses 2 m above the terrain, in the near frame, one of them turned."""
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = [[0.0, 0.0, 2.0], [3.3, 0.4, 2.1], [7.1, -0.7, 2.0]]
    poses[2, :2, :2] = [[0.8, -0.6], [0.6, 0.8]]
    return poses


def translated(poses: np.ndarray) -> np.ndarray:
    far = poses.copy()
    far[:, :3, 3] += OFFSET
    return far


def assert_same_scan(near_log, far_log) -> None:
    """Same hits and ranges within RANGE_TOLERANCE, but for at most 1e-4 of the rays: a ray grazing an edge,
    which float32 rounding in a frame 1 m off the near one decides (measured 1 ray of 86,784 where the code
    before had 4,617 hit/miss flips and a median range error of 5.7 cm)."""
    assert near_log.hit.sum() > 10000
    with np.errstate(invalid="ignore"):
        close = np.abs(far_log.ranges - near_log.ranges) <= RANGE_TOLERANCE
    agree = (near_log.hit == far_log.hit) & (~near_log.hit | close)
    assert (~agree).mean() <= 1e-4, f"{(~agree).sum()} of {agree.size} rays differ"


def test_simulate_far_scene_and_poses_gives_the_scans_at_the_origin(scene_files):
    near, far = scene_files
    poses = drive_poses()
    near_log = mi_lidar.simulate(mi_lidar.load_scene(near), "vlp16", poses, seed=3)
    far_log = mi_lidar.simulate(mi_lidar.load_scene(far), "vlp16", translated(poses), seed=3)
    assert_same_scan(near_log, far_log)
    np.testing.assert_array_equal(far_log.poses, translated(poses))  # the log keeps the poses as given
    both = near_log.hit & far_log.hit
    error = np.linalg.norm(far_log.points_world()[both] - OFFSET - near_log.points_world()[both], axis=-1)
    assert np.quantile(error, 0.9999) <= 1e-3  # m, world points of the log given back in the world frame


def test_render_and_default_pose_of_a_far_scene_match_the_origin(scene_files):
    near, far = scene_files
    near_scene, far_scene = mi_lidar.load_scene(near), mi_lidar.load_scene(far)
    a, b = np.array(mi.render(near_scene, seed=0)), np.array(mi.render(far_scene, seed=0))
    np.testing.assert_array_equal(a[..., 1], b[..., 1])
    hit = a[..., 1] > 0
    np.testing.assert_allclose(b[..., 0][hit], a[..., 0][hit], rtol=0, atol=RANGE_TOLERANCE)
    far_log = mi_lidar.simulate(far_scene, seed=0)  # the scene sensor's pose, given back in the world
    near_log = mi_lidar.simulate(near_scene, seed=0)
    np.testing.assert_allclose(far_log.poses, translated(near_log.poses), rtol=0, atol=1e-9)
    assert_same_scan(near_log, far_log)


def test_render_command_writes_points_in_the_world(scene_files, tmp_path):
    near, far = scene_files
    for xml in (near, far):
        result = invoke_at_80(["render", xml, "--out", tmp_path / xml.stem])
        assert result.exit_code == 0, result.output

    def points(name):
        vertex = plyfile.PlyData.read(str(tmp_path / name / "points.ply"))["vertex"]
        return np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)

    near_points, far_points = points("near"), points("far")
    assert len(near_points) == len(far_points) > 10000
    np.testing.assert_allclose(far_points - OFFSET, near_points, rtol=0, atol=1e-3)


def test_a_mesh_file_in_utm_coordinates_is_refused_with_the_value_and_the_fix(tmp_path):
    vertices = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]]) + OFFSET
    write_mesh_ply(tmp_path / "utm.ply", vertices, [[0, 1, 2]])
    xml = tmp_path / "scene.xml"
    xml.write_text('<scene version="3.0.0"><shape type="ply"><string name="filename" value="utm.ply"/></shape></scene>')
    with pytest.raises(SceneError, match=r"scene.xml: vertex coordinates reach 4,000,010 m; float32 keeps 0.25 m"):
        mi_lidar.load_scene(xml)
    result = invoke_at_80(["render", xml, "--out", tmp_path / "out"])
    assert result.exit_code == 2
    message = " ".join(result.output.split())
    assert "vertex coordinates reach 4,000,010 m; float32 keeps 0.25 m there. Move the scene near the origin" in message
    assert "<translate .../>" in message


def test_poses_far_from_a_scene_at_the_origin_are_refused(scene_files):
    near, _ = scene_files
    with pytest.raises(
        PoseError, match=r"sensor positions relative to the scene reach 4,000,000 m; float32 keeps 0.25"
    ):
        mi_lidar.simulate(mi_lidar.load_scene(near), "vlp16", translated(drive_poses()), seed=0)


def write_las(path: Path, points: np.ndarray) -> Path:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = np.floor(points.min(axis=0)), np.full(3, 1e-4)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    las.write(str(path))
    return path


@pytest.fixture(scope="module")
def clouds(scene_files, tmp_path_factory) -> tuple[Path, Path, np.ndarray]:
    """One simulated VLP-16 scan's returns as a LAS at the origin (bounding box centred there) and in UTM."""
    near, _ = scene_files
    log = mi_lidar.simulate(mi_lidar.load_scene(near), "vlp16", drive_poses()[:1], seed=3)
    points = log.points_world()[log.hit].astype(np.float64)
    points -= np.round((points.min(axis=0) + points.max(axis=0)) / 2)
    folder = tmp_path_factory.mktemp("clouds")
    return write_las(folder / "near.las", points), write_las(folder / "far.las", points + OFFSET), points


def test_a_utm_cloud_reads_at_a_local_origin_and_writes_back_in_utm(clouds, tmp_path):
    _, far, points = clouds
    log = read_any(far)
    np.testing.assert_array_equal(log.poses[0, :3, 3], OFFSET)
    assert np.nanmax(log.ranges) < 100  # ranges from the local origin, not 4e6 m from the world's
    np.testing.assert_allclose(log.points_world()[log.hit], points + OFFSET, rtol=0, atol=1e-4)
    for suffix in (".las", ".ply", ".pcd"):
        back = read_any(write_any(log, tmp_path / f"back{suffix}"))
        np.testing.assert_allclose(back.points_world()[back.hit], points + OFFSET, rtol=0, atol=1e-4, err_msg=suffix)


def read_assets(folder: Path) -> dict[str, np.ndarray]:
    vertices = {}
    for path in sorted((folder / "scene_assets").glob("*.ply")):
        vertex = plyfile.PlyData.read(str(path))["vertex"]
        vertices[path.name] = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    return vertices


def test_fit_scene_of_a_utm_cloud_fits_the_same_scene_up_to_the_translation(clouds, tmp_path):
    near, far, _ = clouds
    fit_scene(near, tmp_path / "near", preview=False)
    fit_scene(far, tmp_path / "far", preview=False)
    a, b = read_assets(tmp_path / "near"), read_assets(tmp_path / "far")
    assert sorted(a) == sorted(b) and len(a) > 2
    for name in a:
        np.testing.assert_allclose(b[name], a[name], rtol=0, atol=1e-4, err_msg=name)  # local coordinates
    far_scene = mi_lidar.load_scene(tmp_path / "far" / "scene.xml")
    near_scene = mi_lidar.load_scene(tmp_path / "near" / "scene.xml")
    near_log = mi_lidar.simulate(near_scene, "vlp16", drive_poses()[:2], seed=1)
    far_log = mi_lidar.simulate(far_scene, "vlp16", translated(drive_poses()[:2]), seed=1)
    assert_same_scan(near_log, far_log)


def test_a_far_log_scores_in_its_far_scene_as_at_the_origin(scene_files):
    """compare, diagnose, calibrate and fit-sensor build their rays with LogRays.from_log(log, scene=scene)."""
    near, far = scene_files
    poses = drive_poses()[:2]
    scores = []
    for xml, shifted in ((near, poses), (far, translated(poses))):
        scene = mi_lidar.load_scene(xml)
        log = mi_lidar.simulate(scene, "vlp16", shifted, seed=1)
        model = scene_sensor_model(scene)[0]
        scores.append(score_log(scene, model, LogRays.from_log(log, scene=scene)))
    np.testing.assert_array_equal(np.isfinite(scores[0]), np.isfinite(scores[1]))
    assert abs(np.mean(scores[1]) - np.mean(scores[0])) < 1e-4  # nats per ray; measured 7e-6 through `compare`


def test_a_camera_renders_a_far_scene_as_at_the_origin(scene_files):
    near, far = scene_files
    images = []
    for xml, shift in ((near, np.zeros(3)), (far, OFFSET)):
        camera = PinholeCamera.look_at(shift + [-8.0, -3.0, 3.0], shift + [5.0, 2.0, 0.0], width=32, height=24)
        images.append(render_camera(mi_lidar.load_scene(xml), camera, spp=2, seed=0))
    assert images[0].mean() > 0.05  # the scene is lit and in view
    assert np.abs(images[1] - images[0]).mean() < 1e-3 * images[0].mean()  # measured 5e-9 (before: 0.035)


@pytest.mark.parametrize(
    "steps",
    [
        '<scale x="2" y="0.5" z="3"/><rotate x="1" y="2" z="0.5" angle="37"/><translate value="4, -5, 6"/>',
        '<lookat origin="1, 2, 3" target="4, 0, -1" up="0, 0, 1"/><scale value="2"/>',
        '<matrix value="0 -1 0 1  1 0 0 2  0 0 1 3  0 0 0 1"/><rotate z="1" angle="$turn"/>',
    ],
)
def test_to_world_steps_are_read_as_mitsuba_reads_them(steps):
    """The float64 reading of a transform that the loader moves to a local origin equals Mitsuba's own."""
    xml = f'<transform name="to_world">{steps}</transform>'
    ours = to_world_matrix(ET.fromstring(xml), {"turn": "25"})

    def cube_vertices(transform: str) -> np.ndarray:
        scene = f'<scene version="3.0.0"><default name="turn" value="25"/><shape type="cube">{transform}</shape>'
        scene += "</scene>"
        return np.array(mi.traverse(mi.load_string(scene).shapes()[0])["vertex_positions"], np.float64).reshape(-1, 3)

    expected = cube_vertices(xml)  # Mitsuba's float32 transform applied to the unit cube
    unit = cube_vertices("")
    np.testing.assert_allclose(unit @ ours[:3, :3].T + ours[:3, 3], expected, rtol=0, atol=1e-5)


def test_a_pose_file_keeps_georeferenced_positions(tmp_path):
    poses = translated(drive_poses())
    poses[:, :3, 3] += 0.123456  # sub-millimetre digits a 10-digit file would round (by 0.32 mm at 4e6 m)
    back = read_poses(write_kitti_poses(tmp_path / "poses.txt", poses))
    np.testing.assert_allclose(back, poses, rtol=0, atol=1e-6)


DATASET_SPEC = """name: geo
seed: 1
rig:
  lidars: [{name: top, pattern: vlp16, mount: {xyz: [0, 0, 1.8]}}]
  cameras: [{name: front, width: 48, height: 32, fov_deg: 80, mount: {xyz: [0.5, 0, 1.6]}}]
scenes:
  - name: offroad
    xml: XML
    frames: 2
    labels: {1: terrain, 5: vegetation, 6: vegetation}
    objects: [{class: Car, shapes: [rock]}]
    trajectory: {waypoints: [[X0, Y], [X1, Y]]}
output: {spp: 2, overlays: false, semantic_ids: {terrain: 72}}
"""


def test_a_dataset_in_utm_renders_the_frames_of_the_origin(tmp_path):
    """The runner's ego z comes from the trajectory (0 for an XML scene), so the scene moves in x and y only."""
    shift = np.array([OFFSET[0], OFFSET[1], 0.0])
    outputs = []
    for name, where in (("near", np.zeros(3)), ("far", shift)):
        xml = tmp_path / f"{name}.xml"
        xml.write_text(offroad_xml(where))
        text = DATASET_SPEC.replace("XML", str(xml)).replace("X0", str(where[0] - 10)).replace("X1", str(where[0] + 10))
        (tmp_path / f"{name}.yaml").write_text(text.replace("Y", str(where[1])))
        run_dataset(load_spec(tmp_path / f"{name}.yaml"), tmp_path / name, serial=True)
        outputs.append(tmp_path / name)
    near, far = outputs
    for frame in ("000000", "000001"):
        a, b = (np.fromfile(d / "velodyne" / f"{frame}.bin", np.float32).reshape(-1, 4) for d in (near, far))
        assert len(a) == len(b) > 10000
        np.testing.assert_allclose(b[:, :3], a[:, :3], rtol=0, atol=1e-3)  # sensor frame; measured 2.3e-5 m
        a, b = (np.fromfile(d / "labels" / f"{frame}.label", np.uint32) for d in (near, far))
        np.testing.assert_array_equal(a, b)
        a, b = ((d / "label_2" / f"{frame}.txt").read_text() for d in (near, far))
        assert a.startswith("Car ") and a == b  # the box seen by the camera, in its frame
    a, b = (np.loadtxt(d / "poses.txt").reshape(-1, 3, 4) for d in (near, far))
    np.testing.assert_allclose(b[:, :, 3] - shift, a[:, :, 3], rtol=0, atol=1e-6)


def test_a_utm_cloud_is_not_written_to_a_float32_format(clouds, tmp_path):
    _, far, _ = clouds
    result = invoke_at_80(["convert", far, tmp_path / "far.bin"])
    assert result.exit_code == 2
    message = " ".join(result.output.split())
    assert "KITTI .bin stores float32 and the points reach 4,000,030 m; float32 keeps 0.25 m there." in message
    assert "Write .las, .ply or .pcd" in message
    assert not (tmp_path / "far.bin").exists()


def shifted_scene(path: Path, shift) -> str:
    """The scene file ``path`` with every shape and sensor moved by ``shift`` (m), as a surveyor would write it:
    a ``translate`` appended to each ``to_world``, a sphere's or cylinder's own points moved, a shape placed by
    neither given a ``to_world``; relative asset paths made absolute."""
    x, y, z = (repr(float(v)) for v in shift)
    root = ET.fromstring(path.read_text())
    for element in root:
        if element.tag not in ("shape", "sensor"):
            continue
        transform = element.find("transform[@name='to_world']")
        points = [p for p in element.findall("point") if p.attrib.get("name") in ("center", "p0", "p1")]
        if transform is not None:
            ET.SubElement(transform, "translate", x=x, y=y, z=z)
        elif points:
            for point in points:
                point.attrib.update({a: repr(float(point.attrib.get(a, 0)) + float(v)) for a, v in zip("xyz", shift)})
        else:
            ET.SubElement(ET.SubElement(element, "transform", name="to_world"), "translate", x=x, y=y, z=z)
        for name in element.findall("string[@name='filename']"):
            name.attrib["value"] = str((path.parent / name.attrib["value"]).resolve())
    return ET.tostring(root, encoding="unicode")


def test_a_far_scene_of_spheres_and_cylinders_gives_the_scans_at_the_origin(tmp_path):
    """The urban street (cubes and a rectangle placed by to_world, lamp poles by their cylinders' ends, trees as
    an ellipsoid file) moved to UTM scans as at the origin. Before, the poles' ends were left in the world frame
    and the scene was refused ("vertex coordinates reach 3,999,994 m")."""
    near, far = (tmp_path / name for name in ("near.xml", "far.xml"))
    near.write_text(shifted_scene(SCENES / "urban_street.xml", np.zeros(3)))
    far.write_text(shifted_scene(SCENES / "urban_street.xml", OFFSET))
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = [[0.0, 0.0, 1.8], [3.0, 0.5, 1.8], [-4.0, -1.0, 1.8]]
    near_log = mi_lidar.simulate(mi_lidar.load_scene(near), "vlp16", poses, seed=3)
    far_log = mi_lidar.simulate(mi_lidar.load_scene(far), "vlp16", translated(poses), seed=3)
    assert_same_scan(near_log, far_log)
    poles = near_log.attributes["label"] == 3
    assert (near_log.hit & poles).sum() > 50  # the cylinders are in the scans


def test_a_far_scene_placed_by_points_alone_loads_at_a_local_origin(tmp_path):
    """A scene whose only far shapes are placed by their own points (no to_world anywhere in the file) is rebased
    too: before, the loader skipped files without the text 'to_world' and refused this one."""
    path = tmp_path / "poles.xml"
    x, y = (float(v) for v in OFFSET[:2])
    path.write_text(
        f"""<scene version="3.0.0">
        <shape type="cylinder" id="pole"><point name="p0" x="{x!r}" y="{y!r}" z="0"/>
            <point name="p1" x="{x!r}" y="{y!r}" z="6"/><float name="radius" value="0.12"/></shape>
        <shape type="sphere" id="ball"><point name="center" x="{x + 5.0!r}" y="{y!r}" z="1"/></shape>
    </scene>"""
    )
    scene = mi_lidar.load_scene(path)
    placed = np.array([[x, y, 0.0], [x, y, 6.0], [x + 5.0, y, 1.0]])  # the points that place the shapes
    np.testing.assert_array_equal(scene_origin(scene), np.round((placed.min(axis=0) + placed.max(axis=0)) / 2))
    assert max(abs(v) for v in (*scene.bbox().min, *scene.bbox().max)) < 10


def write_float32_ply(path: Path, points: np.ndarray) -> Path:
    vertex = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")]).write(str(path))
    return path


def test_a_utm_cloud_stored_in_float32_reads_with_a_warning(clouds, tmp_path):
    """A file that kept UTM coordinates in float32 already lost them to 0.25-0.5 m: the reader says so (the
    points are still read), and the CLI prints it as one warning line. Doubles, or float32 near the origin,
    read silently."""
    from mi_lidar.core.errors import CoarseCoordinatesWarning

    _, _, points = clouds
    coarse = write_float32_ply(tmp_path / "utm32.ply", points + OFFSET)
    with pytest.warns(CoarseCoordinatesWarning, match=r"float32 coordinates reach 4,000,0\d\d m; float32 keeps 0.25 m"):
        log = read_any(coarse)
    assert log.hit.sum() == len(points)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CoarseCoordinatesWarning)
        read_any(write_float32_ply(tmp_path / "near32.ply", points))
        read_any(write_any(log, tmp_path / "utm64.ply"))  # written back with double coordinates
    result = invoke_at_80(["info", coarse])
    assert result.exit_code == 0
    message = " ".join(result.output.split())
    assert "warning: " in message and "Export the cloud with double coordinates" in message


def test_a_scene_keeps_its_local_origin_when_its_geometry_is_updated(scene_files):
    """Calibration moves vertices through mi.traverse; the scene's frame must not change with them."""
    _, far = scene_files
    scene = mi_lidar.load_scene(far)
    origin = scene_origin(scene)
    np.testing.assert_array_equal(origin, [500008.0, 4000000.0, 101.0])  # rounded centre of the elements' positions
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    params[key] = params[key] + 0.5
    params.update()
    np.testing.assert_array_equal(scene_origin(scene), origin)
    assert not scene_origin(mi_lidar.load_scene(SCENES / "offroad.xml")).any()
