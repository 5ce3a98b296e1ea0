import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.io import (
    cloud_from_log,
    log_from_points,
    read_any,
    read_bin_log,
    read_las,
    read_pcd,
    read_pcd_log,
    read_rosbag_log,
    write_any,
    write_pcd,
    write_ply,
)
from tests.core.test_strict_json import strict_load

from .conftest import data_file

NUSCENES = "nuscenes/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"


def synthetic_log(height=8, width=64, scans=1, seed=0) -> Log:
    """A spinning-sensor log: rows top to bottom, 20 % misses, intensity attribute."""
    rng = np.random.default_rng(seed)
    elevation = np.radians(np.linspace(10, -20, height))[:, None]
    azimuth = np.linspace(np.pi, -np.pi, width, endpoint=False)[None, :]
    directions = np.stack(
        np.broadcast_arrays(
            np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        ),
        axis=-1,
    )
    ranges = rng.uniform(2, 40, (scans, height, width))
    hit = rng.random(ranges.shape) > 0.2
    times = (
        100.0 + np.arange(scans)[:, None, None] * 0.1 + np.broadcast_to(np.arange(width) * 0.1 / width, ranges.shape)
    )
    return Log(
        poses=np.tile(np.eye(4), (scans, 1, 1)),
        directions=directions[None],
        ranges=np.where(hit, ranges, np.nan),
        hit=hit,
        times=times,
        attributes={"intensity": rng.uniform(0, 255, ranges.shape).astype(np.float32)},
        sensor={"name": "synthetic"},
    )


def test_nuscenes_bin_builds_ring_grid():
    log = read_bin_log(data_file(NUSCENES))
    assert log.shape == (1, 32, 1084)
    assert log.attributes["valid"].all()
    assert abs((1 - log.hit.mean()) - 0.2315) < 1e-3
    assert np.nanmin(log.ranges) >= 1.0
    elevation = np.degrees(np.arcsin(log.directions[0, :, 500, 2]))
    assert np.all(np.diff(elevation) < 0)
    assert 10.0 < elevation[0] < 11.0 and -31.0 < elevation[-1] < -30.0
    np.testing.assert_array_equal(log.attributes["ring"][0, :, 0], np.arange(31, -1, -1))
    records = np.fromfile(data_file(NUSCENES), "<f4").reshape(-1, 5)
    raw = np.linalg.norm(records[:, :3], axis=1).reshape(-1, 32).T[::-1]
    np.testing.assert_allclose(log.ranges[0][log.hit[0]], raw[log.hit[0]], rtol=1e-6)


def test_kitti_bin_is_one_row(tmp_path):
    points = np.random.default_rng(1).normal(size=(50, 3)) * 10
    points[3] = 0.0
    records = np.concatenate([points, np.ones((50, 1))], axis=1).astype("<f4")
    records.tofile(tmp_path / "000000.bin")
    log = read_any(tmp_path / "000000.bin")
    assert log.shape == (1, 1, 50)
    assert log.hit.sum() == 49 and not log.hit[0, 0, 3]
    np.testing.assert_allclose(log.points_sensor()[0, 0][log.hit[0, 0]], points[np.arange(50) != 3], atol=1e-5)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".las", ".exr", ".npz"])
def test_round_trip_keeps_grid_and_ranges(tmp_path, suffix):
    log = synthetic_log()
    back = read_any(write_any(log, tmp_path / f"scan{suffix}"))
    assert back.shape == log.shape
    np.testing.assert_array_equal(back.hit, log.hit)
    tolerance = 2e-4 if suffix == ".las" else 1e-5
    np.testing.assert_allclose(back.ranges[back.hit], log.ranges[log.hit], atol=tolerance)
    np.testing.assert_allclose(back.points_sensor()[back.hit], log.points_sensor()[log.hit], atol=tolerance)
    np.testing.assert_allclose(back.attributes["intensity"][back.hit], log.attributes["intensity"][log.hit], atol=1e-3)
    if suffix in (".exr", ".pcd", ".npz"):  # organized formats keep the miss directions too
        np.testing.assert_allclose(back.directions, log.directions, atol=1e-5)
    np.testing.assert_allclose(back.times[back.hit], log.times[log.hit], atol=1e-5)
    assert [p.name for p in tmp_path.iterdir()] == [f"scan{suffix}"]


def test_a_scan_too_wide_for_las_integers_is_refused(tmp_path):
    """A hit 300 km away raised laspy's OverflowError ('Values given do not fit after applying offset and scale')
    as a traceback; the file is not written."""
    log = synthetic_log(height=4, width=16)
    log.ranges[0, 0, 0], log.hit[0, 0, 0] = 3e5, True
    with pytest.raises(LogFormatError, match=r"far.las: the hits of scan 0 span \d{3},\d{3} m along [xyz]; LAS stores"):
        write_any(log, tmp_path / "far.las")
    assert list(tmp_path.iterdir()) == []


def test_a_stray_far_point_does_not_move_a_sensor_frame_scan(tmp_path):
    """One point 70 km away made the whole scan 'georeferenced': the sensor moved to the centre of the bounding
    box, 35 km off, and every range read about 35,000 m (info: 'range min / median / max 34882 / 34963 / 35039')."""
    log = synthetic_log(height=4, width=16)
    cloud = cloud_from_log(log)
    points = np.stack([cloud.pop(c) for c in "xyz"], axis=1).astype(np.float64)
    points[7] = (7e4, 0.0, 0.0)
    back = read_any(write_ply(tmp_path / "stray.ply", points, cloud))
    np.testing.assert_array_equal(back.poses[0], np.eye(4))
    ranges = back.ranges[back.hit]
    np.testing.assert_allclose(np.delete(ranges, 7), np.delete(log.ranges[log.hit], 7), rtol=1e-6)
    assert ranges[7] == pytest.approx(7e4)


def test_read_las_gives_the_written_hits_and_attributes(tmp_path):
    log = synthetic_log()
    points, attributes, start = read_las(write_any(log, tmp_path / "scan.las"))
    cloud = cloud_from_log(log)
    expected = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    np.testing.assert_allclose(points, expected, atol=1e-4)  # 0.1 mm coordinate resolution
    np.testing.assert_allclose(attributes["intensity"], cloud["intensity"], atol=1e-6)
    np.testing.assert_array_equal(attributes["ring"], cloud["ring"])
    np.testing.assert_array_equal(attributes["column"], cloud["column"])
    assert start == pytest.approx(log.times[0].min(), abs=1e-6)
    np.testing.assert_allclose(attributes["time"], cloud["time"], atol=1e-6)


def test_kitti_bin_round_trip_writes_hits_only(tmp_path):
    log = synthetic_log()
    back = read_any(write_any(log, tmp_path / "s.bin"))
    assert back.shape == (1, 1, int(log.hit.sum()))
    np.testing.assert_allclose(back.points_sensor()[0, 0], log.points_sensor()[log.hit], atol=1e-5)


def test_miss_directions_are_estimated_from_the_pattern():
    log = synthetic_log(height=4, width=32)
    cloud = cloud_from_log(log, organized=True)
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    back = log_from_points(points, ring=cloud["ring"], column=cloud["column"])
    np.testing.assert_array_equal(back.hit, log.hit)
    np.testing.assert_allclose(back.directions[~back.hit], log.directions[0][~log.hit[0]], atol=1e-6)


def test_rosbag_round_trip_and_fields(tmp_path):
    from rosbags.highlevel import AnyReader

    log = synthetic_log(scans=3)
    path = write_any(log, tmp_path / "bag")
    back = read_rosbag_log(path)
    assert back.shape == log.shape
    np.testing.assert_array_equal(back.hit, log.hit)
    np.testing.assert_allclose(back.ranges[back.hit], log.ranges[log.hit], atol=1e-5)
    np.testing.assert_allclose(back.times, log.times, atol=1e-5)
    with AnyReader([path]) as reader:
        (connection,) = [c for c in reader.connections if c.topic == "/points"]
        msg = reader.deserialize(next(reader.messages([connection]))[2], connection.msgtype)
    assert [f.name for f in msg.fields][:5] == ["x", "y", "z", "intensity", "ring"]
    assert (msg.height, msg.width, msg.is_dense) == (8, 64, False)
    with pytest.raises(FileExistsError):
        write_any(log, path)


def test_rosbag_carries_the_poses_on_tf(tmp_path):
    from rosbags.highlevel import AnyReader
    from scipy.spatial.transform import Rotation

    log = synthetic_log(scans=3)
    log.poses[:, :3, :3] = Rotation.from_euler("zyx", [[0.3, 0.1, 0], [1.2, 0, -0.2], [-2.5, 0.05, 0.1]]).as_matrix()
    log.poses[:, :3, 3] = [[1, 2, 3], [4, 5, 6], [-7, 8, 0.5]]
    path = write_any(log, tmp_path / "bag")
    with AnyReader([path]) as reader:
        topics = {c.topic: c for c in reader.connections}
        assert "transient_local" in str(topics["/tf_static"].ext.offered_qos_profiles).lower()
        clouds = [t for _, t, _ in reader.messages([topics["/points"]])]
        tf = [(t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages([topics["/tf"]])]
        static = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages([topics["/tf_static"]])]
    assert [t for t, _ in tf] == clouds
    for index, (_, message) in enumerate(tf):
        (stamped,) = message.transforms
        assert (stamped.header.frame_id, stamped.child_frame_id) == ("map", "base_link")
        q, v = stamped.transform.rotation, stamped.transform.translation
        np.testing.assert_allclose(
            Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), log.poses[index, :3, :3], atol=1e-12
        )
        np.testing.assert_allclose([v.x, v.y, v.z], log.poses[index, :3, 3])
    (mount,) = static[0].transforms
    assert (mount.header.frame_id, mount.child_frame_id, len(static)) == ("base_link", "lidar", 1)
    assert mount.transform.rotation.w == 1.0


def test_rosbag_round_trip_keeps_poses_and_attributes(tmp_path):
    """Our reader gives back what the bag carries: poses (from /tf), every attribute, invalid cells.

    It dropped both: read back, a scan 2 m along x was placed at the origin, and label, element_id... were gone.
    """
    from scipy.spatial.transform import Rotation

    log = synthetic_log(scans=3)
    log.poses[:, :3, :3] = Rotation.from_euler("z", [[0.0], [0.4], [-1.1]]).as_matrix()
    log.poses[:, :3, 3] = [[0, 0, 2], [2, 0, 2], [4, 1, 2.5]]
    rng = np.random.default_rng(3)
    log.attributes["label"] = rng.integers(0, 7, log.shape).astype(np.int32)
    log.attributes["element_id"] = rng.integers(-1, 2**40, log.shape)  # int64 beyond int32: FLOAT64 on the wire
    log.attributes["cos_incidence"] = rng.random(log.shape).astype(np.float32)
    log.attributes["valid"] = rng.random(log.shape) > 0.1
    back = read_rosbag_log(write_any(log, tmp_path / "bag"))
    np.testing.assert_allclose(back.poses, log.poses, atol=1e-12)
    np.testing.assert_allclose(back.points_world()[log.hit], log.points_world()[log.hit], atol=1e-4)
    for name in ("label", "element_id", "cos_incidence", "intensity", "valid"):
        np.testing.assert_array_equal(back.attributes[name], log.attributes[name], err_msg=name)
    assert back.attributes["label"].dtype == np.int32 and back.attributes["valid"].dtype == bool


def test_a_bag_folder_named_dot_bag_reads_back(tmp_path):
    """``convert log.npz drive.bag`` writes a ROS 2 bag folder called ``drive.bag``; reading it failed with
    "Could not open file 'drive.bag': Is a directory" (rosbags takes every ``*.bag`` for a ROS 1 file)."""
    log = synthetic_log(scans=2)
    path = write_any(log, tmp_path / "drive.bag")
    assert path.is_dir()
    back = read_any(path)
    np.testing.assert_allclose(back.points_world()[log.hit], log.points_world()[log.hit], atol=1e-4)


@pytest.mark.parametrize("per_scan", [False, True])
def test_rosbag_round_trip_keeps_the_sensor_metadata_and_ray_origins(tmp_path, per_scan):
    """The bag carried neither: read back, ``sensor`` was only the topic, bag and frame, and every ray started at
    the sensor's origin (ranges and directions measured from there)."""
    from rosbags.highlevel import AnyReader

    log = synthetic_log(scans=3)
    log.sensor = {
        "name": "os1-32",
        "pattern": "os1-32",
        "max_range_m": 120.0,
        "min_range_m": float("inf"),
        "beam_angles_rad": [0.1, -0.2],
        "effects": ["range_bias(bias=0.05)"],
        "seed": 3,
    }
    rng = np.random.default_rng(5)
    log.origins = rng.normal(scale=0.02, size=(3 if per_scan else 1, 8, 64, 3)).astype(np.float32)
    path = write_any(log, tmp_path / "bag")
    back = read_rosbag_log(path)
    assert back.sensor == log.sensor
    shape = (*log.shape, 3)
    np.testing.assert_array_equal(np.broadcast_to(back.origins, shape), np.broadcast_to(log.origins, shape))
    np.testing.assert_array_equal(back.hit, log.hit)
    np.testing.assert_allclose(back.ranges[log.hit], log.ranges[log.hit], atol=1e-5)
    directions = np.broadcast_to(log.directions, shape)
    np.testing.assert_allclose(back.directions[log.hit], directions[log.hit], atol=1e-5)
    np.testing.assert_allclose(back.points_sensor()[log.hit], log.points_sensor()[log.hit], atol=1e-5)
    with AnyReader([path]) as reader:  # what a ROS user finds: a latched JSON string and three more fields
        topics = {c.topic: c for c in reader.connections}
        info = topics["/points/sensor_info"]
        assert info.msgtype == "std_msgs/msg/String" and "transient_local" in str(info.ext.offered_qos_profiles).lower()
        (text,) = [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages([info])]
        cloud = reader.deserialize(next(reader.messages([topics["/points"]]))[2], "sensor_msgs/msg/PointCloud2")
    sent = strict_load(text)  # JSON for any ROS user: it held Infinity
    assert sent["max_range_m"] == 120.0 and sent["min_range_m"] is None
    assert [f.name for f in cloud.fields][-3:] == ["origin_x", "origin_y", "origin_z"]


def test_rosbag_without_ray_origins_has_no_origin_fields(tmp_path):
    from rosbags.highlevel import AnyReader

    path = write_any(synthetic_log(scans=2), tmp_path / "bag")
    with AnyReader([path]) as reader:
        (points,) = [c for c in reader.connections if c.topic == "/points"]
        cloud = reader.deserialize(next(reader.messages([points]))[2], points.msgtype)
    assert not {f.name for f in cloud.fields} & {"origin_x", "origin_y", "origin_z"}
    assert read_rosbag_log(path).sensor == {"name": "synthetic"}


def test_rosbag_sensor_info_that_is_not_an_object_is_refused(tmp_path, monkeypatch):
    import mi_lidar.io.rosbag as rosbag

    monkeypatch.setattr(rosbag, "dumps_exact", lambda sensor: "[1, 2]")
    path = write_any(synthetic_log(scans=2), tmp_path / "bag")
    with pytest.raises(LogFormatError, match=r"bag: /points/sensor_info holds a list; expected an object"):
        read_rosbag_log(path)


def test_rosbag_poses_resolve_a_tf_chain_at_the_cloud_stamp(tmp_path):
    from mi_lidar.io.rosbag import _frame_pose

    shift = lambda x: np.array([[1, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    tree = {"base": [(10, "odom", shift(1.0)), (20, "odom", shift(2.0))], "lidar": [(-1, "base", shift(0.5))]}
    assert _frame_pose(tree, "lidar", 15)[0, 3] == 1.5  # the latest transform at or before the stamp
    assert _frame_pose(tree, "lidar", 25)[0, 3] == 2.5 and _frame_pose(tree, "lidar", 5)[0, 3] == 1.5
    np.testing.assert_array_equal(_frame_pose(tree, "camera", 15), np.eye(4))  # no transform: identity


def test_open3d_reads_our_point_clouds(tmp_path):
    o3d = pytest.importorskip("open3d")
    log = synthetic_log()
    for suffix in (".pcd", ".ply"):
        cloud = o3d.io.read_point_cloud(str(write_any(log, tmp_path / f"s{suffix}")), remove_nan_points=True)
        np.testing.assert_allclose(np.asarray(cloud.points), log.points_sensor()[log.hit], atol=1e-5)


def test_pcd_ascii_and_binary_compressed(tmp_path):
    o3d = pytest.importorskip("open3d")
    points = np.random.default_rng(2).normal(size=(300, 3)) * 5
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.io.write_point_cloud(str(tmp_path / "c.pcd"), cloud, write_ascii=False, compressed=True)
    assert b"DATA binary_compressed" in (tmp_path / "c.pcd").read_bytes()[:400]
    fields, width, height = read_pcd(tmp_path / "c.pcd")
    np.testing.assert_allclose(np.stack([fields[c] for c in "xyz"], 1), points, atol=1e-12)
    write_pcd(tmp_path / "a.pcd", {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}, binary=False)
    log = read_pcd_log(tmp_path / "a.pcd")
    assert log.shape == (1, 1, 300)
    np.testing.assert_allclose(log.points_sensor()[0, 0], points, rtol=1e-6, atol=1e-6)  # Log stores float32


def test_inconsistent_ring_fields_are_rejected(tmp_path):
    points = np.ones((3, 3))
    with pytest.raises(LogFormatError, match="share a"):
        log_from_points(points, ring=np.array([0, 0, 1]), column=np.array([0, 0, 0]))
    with pytest.raises(LogFormatError, match=r"field 'ring' must hold non-negative integers; point 1 has -1"):
        log_from_points(points, ring=np.array([0, -1, 1]))
    with pytest.raises(LogFormatError, match="field 'column' of point 2 is 1.09951e"):
        log_from_points(points, ring=np.array([0, 1, 2]), column=np.array([0, 1, 2**40]))
    with pytest.raises(LogFormatError, match="grid for only 3 points"):
        log_from_points(points, ring=np.array([0, 1, 2]), column=np.array([0, 1, 2**20]))


@pytest.mark.parametrize("field", ["ring", "column"])
def test_a_ring_or_column_beyond_int64_is_refused(tmp_path, field):
    """A float64 column of 1e30 wrapped to index -2**63 when cast: IndexError (index -9223372036854775808 is out of
    bounds for axis 1) as a traceback."""
    log = synthetic_log(height=4, width=16)
    cloud = cloud_from_log(log)
    cloud[field] = cloud[field].astype(np.float64)
    cloud[field][7] = 1e30
    points = np.stack([cloud.pop(c) for c in "xyz"], axis=1)
    write_ply(tmp_path / "far.ply", points, cloud)
    with pytest.raises(LogFormatError, match=rf"far.ply: field '{field}' of point 7 is 1e\+30; ring and column"):
        read_any(tmp_path / "far.ply")


def test_ros1_bag_with_unorganized_ring_cloud(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = store.types
    field = types["sensor_msgs/msg/PointField"]
    rng = np.random.default_rng(3)
    ring = np.tile(np.arange(4, dtype=np.uint16), 10)
    elevation = np.radians(-10.0 + 5 * ring)
    azimuth = np.repeat(np.linspace(0, 1, 10), 4)
    distance = rng.uniform(2, 10, 40)
    xyz = distance[:, None] * np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    record = np.dtype(
        {
            "names": ["x", "y", "z", "ring"],
            "formats": ["<f4", "<f4", "<f4", "<u2"],
            "offsets": [0, 4, 8, 16],
            "itemsize": 20,
        }
    )
    table = np.zeros(40, record)
    table["x"], table["y"], table["z"], table["ring"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], ring
    msg = types["sensor_msgs/msg/PointCloud2"](
        header=types["std_msgs/msg/Header"](
            seq=0, stamp=types["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="velodyne"
        ),
        height=1,
        width=40,
        fields=[
            field(name=n, offset=o, datatype=d, count=1)
            for n, o, d in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("ring", 16, 4))
        ],
        is_bigendian=False,
        point_step=20,
        row_step=800,
        data=np.frombuffer(table.tobytes(), np.uint8),
        is_dense=True,
    )
    with Writer(tmp_path / "v.bag") as writer:
        connection = writer.add_connection("/velodyne_points", msg.__msgtype__, typestore=store)
        writer.write(connection, 5_000_000_000, store.serialize_ros1(msg, msg.__msgtype__))
    log = read_any(tmp_path / "v.bag")
    assert log.shape == (1, 4, 10)
    np.testing.assert_array_equal(log.attributes["ring"][0, :, 0], [3, 2, 1, 0])
    np.testing.assert_allclose(log.ranges[0, ::-1].T.ravel(), distance, rtol=1e-5)
    assert np.all(log.times == 5.0)
