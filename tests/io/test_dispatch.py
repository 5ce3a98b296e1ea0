import json

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.patterns import FiringPattern
from mi_lidar.core.patterns.from_log import pattern_from_log
from mi_lidar.io import convert, info, read_any, read_velodyne, write_any
from mi_lidar.io.commands import scan_period
from mi_lidar.io.dispatch import detect_format

from .conftest import data_file
from .synth import carmen_text, write_ouster
from .test_clouds import synthetic_log


@pytest.mark.parametrize(
    "name, fmt",
    [
        ("a.npz", "npz"),
        ("a.log", "carmen"),
        ("a.log.gz", "carmen"),
        ("a.clf", "carmen"),
        ("a.bin", "bin"),
        ("a.pcd.bin", "bin"),
        ("a.PLY", "ply"),
        ("a.pcd", "pcd"),
        ("a.las", "las"),
        ("a.laz", "las"),
        ("a.bag", "rosbag"),
        ("a.db3", "rosbag"),
        ("a.exr", "exr"),
        ("a.pcap", "pcap"),
    ],
)
def test_extension_table(name, fmt):
    assert detect_format(name) == fmt


def test_write_formats_and_errors(tmp_path):
    assert detect_format(tmp_path / "out", for_writing=True) == "rosbag2"
    with pytest.raises(LogFormatError, match="unknown extension '.xyz'"):
        read_any(tmp_path / "a.xyz")
    with pytest.raises(LogFormatError, match="unknown compressed format"):
        read_any(tmp_path / "a.tar.gz")
    (tmp_path / "images").mkdir()  # a folder of something else (e.g. a dataset's): not a ROS 2 bag
    with pytest.raises(LogFormatError, match="images: a folder without metadata.yaml, so not a ROS 2 bag"):
        read_any(tmp_path / "images")
    (tmp_path / "images").rmdir()
    for name, kind in (("scan.exr", "an EXR range image"), ("drive.pcap", "a pcap capture"), ("c.log.gz", "a CARMEN")):
        (tmp_path / name).mkdir()  # was 'a folder without metadata.yaml, so not a ROS 2 bag'
        pattern = rf"{name}: a folder, but its name ends in '\.\w+', which names {kind}"
        with pytest.raises(LogFormatError, match=pattern):
            read_any(tmp_path / name)
        (tmp_path / name).rmdir()
    log = synthetic_log(scans=3)
    with pytest.raises(LogFormatError, match="holds 3 scans and pcd holds one; pass scan="):
        write_any(log, tmp_path / "a.pcd")
    with pytest.raises(LogFormatError, match="cannot write scan 5: the log holds"):
        write_any(log, tmp_path / "a.pcd", scan=5)
    with pytest.raises(LogFormatError, match="cannot write format 'carmen'"):
        write_any(log, tmp_path / "a.log", fmt="carmen")
    with pytest.raises(LogFormatError, match="cannot write format 'pcap'; writable formats: npz"):
        write_any(log, tmp_path / "a.pcap")  # was "unknown extension '.pcap'; supported: ..., .pcap, ..."
    with pytest.raises(
        LogFormatError, match=r"unknown extension '\.xyz'; writable: \.npz, \.bin, [^:]*\.png or a ROS 2 bag"
    ):
        write_any(log, tmp_path / "a.xyz")  # was every extension read (.clf, .log, .pcap), as if written
    assert not any(tmp_path.iterdir())
    back = read_any(write_any(log, tmp_path / "two.pcd", scan=2))
    np.testing.assert_allclose(back.ranges[back.hit], log.ranges[2][log.hit[2]], atol=1e-5)


def test_convert_and_info(tmp_path):
    (tmp_path / "lab.log").write_text(carmen_text(scans=4))
    summary = info(tmp_path / "lab.log")
    assert summary["format"] == "carmen" and summary["shape"] == [4, 180, 1]
    assert summary["miss_fraction"] == pytest.approx(1 / 180)
    assert summary["range_m"][0] == pytest.approx(1.0) and summary["range_m"][2] == pytest.approx(2.79)
    assert summary["scan_period_s"] == pytest.approx(1.0)
    assert summary["trajectory_length_m"] == pytest.approx(3.0)
    json.dumps(summary)
    out = convert(tmp_path / "lab.log", tmp_path / "scan1.ply", scan=1)
    back = read_any(out)
    assert back.hit.sum() == 179
    png = convert(tmp_path / "lab.log", tmp_path / "lab.png", scan=0)
    assert png.read_bytes()[:4] == b"\x89PNG"
    npz = convert(tmp_path / "lab.log", tmp_path / "lab.npz")
    np.testing.assert_array_equal(read_any(npz).hit, read_any(tmp_path / "lab.log").hit)


def test_info_names_a_simulated_logs_pattern_and_seed(tmp_path):
    log = synthetic_log(scans=2)
    log.sensor = {"pattern": "vlp16", "seed": 3, "effects": ["range_bias(bias=0.05)"]}
    summary = info(log.save(tmp_path / "drive.npz"))
    assert summary["sensor"] == "vlp16"  # it said 'unknown': only a reader's 'name' was looked up
    assert summary["simulated"] == {"seed": 3, "effects": ["range_bias(bias=0.05)"]}
    assert summary["scan_period_s"] == pytest.approx(0.1)  # simulated scans are whole
    assert info(convert(tmp_path / "drive.npz", tmp_path / "one.ply", scan=0))["simulated"] is None


def test_scan_period_counts_whole_scans_of_a_capture():
    log = synthetic_log(scans=4)
    log.times[0] += 0.07  # a capture that starts mid-revolution: the first scan is its last 30 %
    assert scan_period(log, streamed=True) == pytest.approx(0.1)
    assert scan_period(log.select(slice(0, 2)), streamed=True) is None
    velodyne = info(data_file("velodyne/velodyne_vlp16.pcap"))  # 552 then 1464 of about 1808 columns
    assert velodyne["shape"] == [2, 16, 1464] and velodyne["scan_period_s"] is None  # it said 0.031 s


def test_pattern_from_real_ouster_frame():
    log = read_any(data_file("ouster/OS-1-32-G_v2.1.1_1024x10.pcap"))
    pattern = pattern_from_log(log)
    assert isinstance(pattern, FiringPattern)
    assert pattern.shape == (32, 1024)
    np.testing.assert_allclose(pattern.directions(), log.directions[0], atol=1e-6)
    np.testing.assert_allclose(pattern.origins(), log.origins[0], atol=1e-7)
    assert pattern.period == pytest.approx(0.1, rel=1e-3)
    np.testing.assert_allclose(np.degrees(pattern.elevation[:, 0]), log.sensor["beam_altitude_deg"], atol=1e-4)


def test_pattern_from_synthetic_ouster_and_velodyne(tmp_path):
    log = read_any(write_ouster(tmp_path, np.full((8, 32), 3000, np.uint32)))
    pattern = pattern_from_log(log)
    assert pattern.time.min() == 0.0 and pattern.time.max() < pattern.period == pytest.approx(0.1)
    velodyne = read_velodyne(data_file("velodyne/velodyne_vlp16.pcap"), data_file("velodyne/VLP16db.yaml"))
    vp = pattern_from_log(velodyne, scan=1)
    np.testing.assert_array_equal(vp.beam_id, velodyne.attributes["laser_id"][1, :, 0])
    np.testing.assert_allclose(vp.directions(), velodyne.directions[1], atol=1e-6)
    assert vp.origin is None
