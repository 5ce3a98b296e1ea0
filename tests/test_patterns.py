"""Firing patterns: vendor tables, timing, geometry, user tables, registry and every error path."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from mi_lidar.core.errors import PatternError
from mi_lidar.core.patterns import (
    PATTERN_NAMES,
    FiringPattern,
    from_table,
    get_pattern,
    ouster,
    packet_32x32,
    planar,
    raster,
    rosette,
    spinning,
    to_table,
)
from mi_lidar.core.patterns.vendor import HDL64E

DATA = (Path(__file__).parents[1] / ".." / "shared" / "data").resolve()
OUSTER_JSON = DATA / "ouster" / "OS-1-32-G_v2.1.1_1024x10.json"
VLP16_YAML = DATA / "velodyne" / "VLP16db.yaml"


def need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(f"real data file {path} is absent (the data folder lives beside the repository in ../shared/data)")
    return path


def assert_valid(p: FiringPattern):
    h, w = p.shape
    assert p.elevation.shape == p.azimuth.shape == p.time.shape == (h, w)
    d = p.directions()
    assert d.dtype == np.float32 and d.shape == (h, w, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-6)
    o = p.origins()
    assert o.dtype == np.float32 and o.shape == (h, w, 3)
    assert p.time.min() >= 0.0 and p.time.max() < p.period


@pytest.mark.parametrize("name", PATTERN_NAMES)
def test_every_named_pattern_is_valid(name):
    p = get_pattern(name)
    assert_valid(p)
    assert p.name == name
    assert not p.elevation.flags.writeable


def test_directions_follow_the_ros_convention():
    p = FiringPattern(
        "t",
        elevation=[[0.0, 0.0, math.pi / 2]],
        azimuth=[[0.0, math.pi / 2, 0.0]],
        time=[[0.0, 0.01, 0.02]],
        period=0.1,
    )
    np.testing.assert_allclose(p.directions()[0], [[1, 0, 0], [0, 1, 0], [0, 0, 1]], atol=1e-7)


@pytest.mark.parametrize(
    "model,lo,hi,lasers,cycle", [("vlp16", -15.0, 15.0, 16, 55.296e-6), ("hdl32e", -30.67, 10.67, 32, 46.08e-6)]
)
def test_velodyne_elevations_and_timing_match_the_manuals(model, lo, hi, lasers, cycle):
    p = spinning(model)
    assert p.shape == (lasers, math.floor(0.1 / cycle))
    el = np.degrees(p.elevation[:, 0])
    assert el.min() == pytest.approx(lo) and el.max() == pytest.approx(hi)
    assert np.all(np.diff(el) < 0), "rows must be sorted by elevation, highest first"
    assert np.all(np.diff(p.time, axis=1) > 0), "timestamps must increase along every beam"
    np.testing.assert_allclose(np.diff(p.time, axis=1), cycle, rtol=1e-9)
    # within one firing, lasers fire in laser-id order at the vendor's spacing
    spacing = cycle / (55.296 / 2.304 if model == "vlp16" else 46.08 / 1.152)
    np.testing.assert_allclose(p.time[:, 0], p.beam_id * spacing, atol=1e-12)


def test_vlp32c_fires_its_lasers_in_pairs():
    p = spinning("vlp32c")
    assert p.shape == (32, math.floor(0.1 / 55.296e-6))
    el = np.degrees(p.elevation[:, 0])
    assert (el.min(), el.max()) == (pytest.approx(-25.0), pytest.approx(15.0))
    assert np.all(np.diff(el) < 0)
    np.testing.assert_allclose(p.time[:, 0], (p.beam_id // 2) * 2.304e-6, atol=1e-12)


def test_the_velodyne_reader_and_the_pattern_share_one_laser_table():
    from mi_lidar.io.velodyne import MODELS

    for name, model in MODELS.items():
        p = spinning(name.replace("-", "").lower())
        assert model.lasers == p.shape[0]
        np.testing.assert_allclose(np.sort(model.elevation_deg)[::-1], np.degrees(p.elevation[:, 0]), atol=1e-9)
        np.testing.assert_allclose(model.sequence_us, np.diff(p.time[0, :2])[0] * 1e6, rtol=1e-9)


def test_vlp16_rows_match_the_recorded_calibration_file():
    text = need(VLP16_YAML).read_text()
    ids = [int(v) for v in re.findall(r"\blaser_id:\s*(\d+)", text)]
    vert = [float(v) for v in re.findall(r"\bvert_correction:\s*([-\d.eE]+)", text)]
    by_id = dict(zip(ids, vert))
    p = spinning("vlp16")
    np.testing.assert_allclose(p.elevation[:, 0], [by_id[k] for k in p.beam_id], atol=1e-9)


def test_spinning_sweeps_clockwise_from_the_back():
    p = spinning("vlp16")
    first = p.beam_id.tolist().index(0)  # laser 0 fires first, pointing backwards
    assert abs(p.azimuth[first, 0]) == pytest.approx(math.pi)
    middle = p.azimuth[:, p.shape[1] // 2]
    assert np.all(np.abs(middle) < math.radians(1.0)), "the middle column looks forward"
    step = np.diff(np.unwrap(p.azimuth[0]))
    assert np.all(step < 0)
    np.testing.assert_allclose(step, -2 * math.pi * 55.296e-6 / 0.1, rtol=1e-9)


def test_spinning_rpm_and_custom_firing_count():
    p = spinning("hdl32e", rpm=1200)
    assert p.period == pytest.approx(0.05) and p.shape == (32, 1085)  # nuScenes: 1084-1085 firings per 20 Hz sweep
    q = spinning("vlp16", n_firings=900)
    assert q.shape == (16, 900)
    np.testing.assert_allclose(np.diff(q.time, axis=1), 0.1 / 900)


def test_hdl64e_uses_the_published_calibration_and_its_beam_origins():
    p = spinning("hdl64e")
    assert p.shape[0] == 64 and sorted(p.beam_id.tolist()) == list(range(64))
    np.testing.assert_allclose(np.degrees(p.elevation[:, 0]), np.asarray(HDL64E.elevation_deg)[p.beam_id])
    assert np.degrees(p.elevation).max() == pytest.approx(1.9601) and np.degrees(p.elevation).min() == pytest.approx(
        -24.5551
    )
    # upper and lower blocks fire together
    upper, lower = p.beam_id.tolist().index(5), p.beam_id.tolist().index(37)
    np.testing.assert_allclose(p.time[upper], p.time[lower])
    # point at range r: origin + r d equals Velodyne's formula in its own frame, turned into ROS axes
    r, i, j = 20.0, upper, 700
    el, az = p.elevation[i, j], p.azimuth[i, j]
    v, h = HDL64E.vertical_offset_m[5], HDL64E.horizontal_offset_m[5]
    a = -az  # Velodyne azimuth, clockwise
    xy = r * math.cos(el) - v * math.sin(el)
    x_v, y_v = xy * math.sin(a) - h * math.cos(a), xy * math.cos(a) + h * math.sin(a)
    z = r * math.sin(el) + v * math.cos(el)
    point = p.origin[i, j] + r * p.directions()[i, j].astype(np.float64)
    np.testing.assert_allclose(point, [y_v, -x_v, z], atol=1e-5)


def test_ouster_rows_equal_the_metadata():
    meta = json.loads(need(OUSTER_JSON).read_text())
    p = ouster(OUSTER_JSON)
    assert p.shape == (32, 1024) and p.period == pytest.approx(0.1)
    np.testing.assert_allclose(np.degrees(p.elevation[:, 0]), meta["beam_altitude_angles"], atol=1e-12)
    assert p.beam_id.tolist() == list(range(32))
    # destaggered: every column looks in one direction to within a pixel; column 0 backwards, the middle forward
    spread = np.ptp(np.unwrap(p.azimuth, axis=0), axis=0)
    assert spread.max() < 2 * math.pi / 1024
    assert np.all(np.abs(np.degrees(p.azimuth[:, 0])) > 170) and np.all(np.abs(np.degrees(p.azimuth[:, 512])) < 5)
    # destaggering moves each row by the metadata's pixel shift
    q = ouster(OUSTER_JSON, destaggered=False)
    for row, shift in enumerate(meta["data_format"]["pixel_shift_by_row"]):
        np.testing.assert_array_equal(p.time[row], np.roll(q.time[row], shift))
        assert np.all(np.diff(np.roll(p.time[row], -shift)) > 0)
    assert get_pattern(str(OUSTER_JSON)).shape == (32, 1024)


def test_ouster_points_follow_the_vendor_formula():
    meta = json.loads(need(OUSTER_JSON).read_text())
    q = ouster(OUSTER_JSON, destaggered=False)  # column = measurement id
    mid = np.arange(1024)
    np.testing.assert_allclose(q.time, np.broadcast_to(mid * 0.1 / 1024, (32, 1024)))
    # manual: x = (r - n) cos(enc + theta) cos(phi) + n cos(enc), ... with theta = -beam azimuth, then lidar -> sensor
    r, n = 7.5, meta["lidar_origin_to_beam_origin_mm"] / 1000
    enc = 2 * math.pi * (1 - mid / 1024)[None, :]
    theta = -np.radians(meta["beam_azimuth_angles"])[:, None]
    phi = np.radians(meta["beam_altitude_angles"])[:, None]
    lidar = np.stack(
        np.broadcast_arrays(
            (r - n) * np.cos(enc + theta) * np.cos(phi) + n * np.cos(enc),
            (r - n) * np.sin(enc + theta) * np.cos(phi) + n * np.sin(enc),
            (r - n) * np.sin(phi),
        ),
        axis=-1,
    )
    transform = np.asarray(meta["lidar_to_sensor_transform"], dtype=np.float64).reshape(4, 4)
    expected = lidar @ transform[:3, :3].T + transform[:3, 3] / 1000
    point = q.origin + r * q.directions().astype(np.float64)
    np.testing.assert_allclose(point, expected, atol=5e-6)


def test_ouster_nested_metadata_layout(tmp_path):
    meta = json.loads(need(OUSTER_JSON).read_text())
    nested = {
        "beam_intrinsics": {
            k: meta[k] for k in ("beam_altitude_angles", "beam_azimuth_angles", "lidar_origin_to_beam_origin_mm")
        },
        "lidar_data_format": meta["data_format"],
        "config_params": {"lidar_mode": "1024x20"},
    }
    path = tmp_path / "nested.json"
    path.write_text(json.dumps(nested))
    p = ouster(path)
    assert p.period == pytest.approx(0.05)
    np.testing.assert_allclose(p.elevation, ouster(OUSTER_JSON).elevation)


def test_ouster_nominal_tables():
    p = ouster(beams=64)
    assert p.shape == (64, 1024)
    np.testing.assert_allclose(np.degrees(p.elevation[[0, -1], 0]), [16.611, -16.611])
    stagger = np.degrees(np.unwrap(ouster(beams=64, destaggered=False).azimuth[:4, 0]))
    np.testing.assert_allclose(stagger - stagger[0], -np.array([3.164, 1.055, -1.055, -3.164]) + 3.164, atol=1e-9)
    assert ouster(beams=128, columns=2048, rpm=1200).shape == (128, 2048)


def test_packet_is_32_yaws_by_32_pitches_over_1_8_degrees():
    p = packet_32x32()
    assert p.shape == (32, 32)
    yaw = np.degrees(p.azimuth[0])
    assert yaw.max() - yaw.min() == pytest.approx(1.8 * 31 / 32)
    assert np.all(np.diff(yaw) < 0)
    np.testing.assert_allclose(p.azimuth, p.azimuth[:1].repeat(32, axis=0))  # 32 pitches at each yaw
    np.testing.assert_allclose(np.degrees(p.elevation[[0, -1], 0]), [10.67, -30.67])
    assert p.period == pytest.approx(552.96e-6)


def test_planar_180_by_1_degree():
    p = get_pattern("planar-180")
    assert p.shape == (180, 1)  # each bearing is a beam, as CARMEN logs are read
    np.testing.assert_allclose(
        np.degrees(p.azimuth[:, 0]), np.arange(-90, 90), atol=1e-9
    )  # CARMEN: theta - pi/2 + i pi/180
    assert np.all(p.elevation == 0) and np.all(np.diff(p.time[:, 0]) > 0)
    q = planar(360)
    np.testing.assert_allclose(np.diff(np.degrees(np.unwrap(q.azimuth[:, 0]))), 1.0)
    np.testing.assert_allclose(np.degrees(planar(4, 90.0, start_deg=10.0).azimuth[:, 0]), [10, 32.5, 55, 77.5])


def test_raster_scans_row_by_row():
    p = raster(h_fov_deg=60, v_fov_deg=20, width=30, height=10, period=0.05)
    assert p.shape == (10, 30)
    assert np.all(np.diff(p.time.ravel()) > 0)
    assert np.degrees(p.elevation).max() == pytest.approx(9.0) and np.degrees(p.azimuth).min() == pytest.approx(-29.0)


def test_rosette_covers_its_fov_and_does_not_repeat():
    fov = 38.4
    p = rosette(n_points=20000, fov_deg=fov)
    assert p.shape == (1, 20000)
    d = p.directions().reshape(-1, 3).astype(np.float64)
    off_axis = np.degrees(np.arccos(np.clip(d[:, 0], -1, 1)))
    assert off_axis.max() == pytest.approx(fov / 2, abs=0.05)
    u, v = np.degrees(np.arctan2(d[:, 1], d[:, 0])), np.degrees(np.arcsin(d[:, 2]))
    edges = np.arange(-fov / 2, fov / 2 + 1e-9, 1.0)
    hist, _, _ = np.histogram2d(u, v, bins=[edges, edges])
    centres = (edges[:-1] + edges[1:]) / 2
    inside = np.hypot(*np.meshgrid(centres, centres, indexing="ij")) < 0.9 * fov / 2
    assert (hist[inside] > 0).mean() > 0.95, "1-degree cells of the field of view left empty"
    unique = np.unique(np.round(d / 1e-4).astype(np.int64), axis=0)
    assert len(unique) > 0.98 * len(d), "a non-repetitive scan should hardly revisit a direction"


@pytest.mark.parametrize("suffix", [".csv", ".npy"])
def test_user_table_round_trip(tmp_path, suffix):
    p = raster(width=12, height=5)
    path = to_table(p, tmp_path / f"mine{suffix}")
    q = from_table(path, period=p.period)
    assert q.name == "mine" and q.shape == p.shape
    np.testing.assert_allclose(q.elevation, p.elevation, atol=1e-14)
    np.testing.assert_allclose(q.azimuth, p.azimuth, atol=1e-14)
    np.testing.assert_allclose(q.time, p.time, atol=1e-15)
    assert get_pattern(path, period=p.period).shape == p.shape


def test_user_csv_without_times_or_grid(tmp_path):
    path = tmp_path / "fan.csv"
    path.write_text("azimuth_deg,elevation_deg\n10,0\n20,1.5\n30,-1.5\n40,0\n")
    p = from_table(path)
    assert p.shape == (1, 4) and p.period == pytest.approx(0.1)
    np.testing.assert_allclose(np.degrees(p.azimuth[0]), [10, 20, 30, 40])
    np.testing.assert_allclose(p.time[0], [0, 0.025, 0.05, 0.075])


def test_user_npy_rows_with_times_infer_the_period(tmp_path):
    path = tmp_path / "rays.npy"
    np.save(path, np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.01], [2.0, 4.0, 0.02]]))
    p = from_table(path)
    assert p.shape == (1, 3) and p.period == pytest.approx(0.03)


# ------------------------------------------------------------------------------------------
# Error paths: every one raises PatternError naming the offending value
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "call,named",
    [
        (lambda: get_pattern("vlp-16"), "'vlp-16'"),
        (lambda: get_pattern("vlp16", speed=3), "speed"),
        (lambda: planar(0), "n_bearings"),
        (lambda: planar(-3), "-3"),
        (lambda: planar(2.5), "2.5"),
        (lambda: planar(360, fov_deg=400), "400"),
        (lambda: planar(360, period=0), "period"),
        (lambda: planar(360, start_deg=float("nan")), "start_deg"),
        (lambda: spinning("hdl128"), "'hdl128'"),
        (lambda: spinning("vlp16", rpm=-600), "-600"),
        (lambda: spinning("vlp16", rpm=2e7), "20000000.0"),
        (lambda: spinning("vlp16", n_firings=4000), "4000"),
        (lambda: ouster(beams=48), "48"),
        (lambda: ouster(columns=0), "columns"),
        (lambda: ouster("/nonexistent/meta.json"), "/nonexistent/meta.json"),
        (lambda: raster(width=0), "width"),
        (lambda: raster(v_fov_deg=200), "200"),
        (lambda: rosette(n_points=0), "n_points"),
        (lambda: rosette(fov_deg=180), "180"),
        (lambda: rosette(petals=0), "petals"),
        (lambda: from_table("/nonexistent/rays.csv"), "/nonexistent/rays.csv"),
        (lambda: from_table("rays.txt"), "rays.txt"),
        (lambda: FiringPattern("bad", [[0.0, float("inf")]], [[0.0, 0.0]], [[0.0, 0.0]], 0.1), "inf"),
        (lambda: FiringPattern("bad", [[2.0]], [[0.0]], [[0.0]], 0.1), "2.0"),
        (lambda: FiringPattern("bad", [[0.0]], [[0.0]], [[0.2]], 0.1), "0.2"),
        (lambda: FiringPattern("bad", [[0.0]], [[0.0, 1.0]], [[0.0]], 0.1), "(1, 2)"),
        (lambda: FiringPattern("bad", [[0.0]], [[0.0]], [[0.0]], 0.1, origin=np.zeros((1, 1, 2))), "(1, 1, 2)"),
        (lambda: FiringPattern("bad", [[0.0]], [[0.0]], [[0.0]], 0.1, beam_id=[0.5]), "float64"),
    ],
)
def test_errors_name_the_value(call, named):
    with pytest.raises(PatternError) as info:
        call()
    assert named in str(info.value)


@pytest.mark.parametrize(
    "text,named",
    [
        ("elevation_deg\n1\n", "azimuth_deg"),
        ("elevation_deg,azimuth_deg\n", "no rays"),
        ("elevation_deg,azimuth_deg\n1,abc\n", "'abc'"),
        ("elevation_deg,azimuth_deg\n1,nan\n", "nan"),
        ("elevation_deg,azimuth_deg,row\n1,2,0\n", "row/col"),
        ("elevation_deg,azimuth_deg,row,col\n1,2,0,0\n1,2,0,0\n", "row=0, col=0"),
        ("elevation_deg,azimuth_deg,row,col\n1,2,0,0\n1,2,1,1\n", "row=0, col=1"),
        ("elevation_deg,azimuth_deg,row,col\n1,2,0,-1\n", "-1"),
        ("elevation_deg,azimuth_deg,time_s\n1,2,-0.5\n", "-0.5"),
        ("elevation_deg,azimuth_deg\n100,0\n", "100.0"),
    ],
)
def test_malformed_csv_is_refused(tmp_path, text, named):
    path = tmp_path / "t.csv"
    path.write_text(text)
    with pytest.raises(PatternError) as info:
        from_table(path)
    assert named in str(info.value)


@pytest.mark.parametrize("array,named", [(np.zeros((4, 5)), "(4, 5)"), (np.array(["a", "b"]), "(2,)")])
def test_malformed_npy_is_refused(tmp_path, array, named):
    path = tmp_path / "t.npy"
    np.save(path, array)
    with pytest.raises(PatternError) as info:
        from_table(path)
    assert named in str(info.value)


@pytest.mark.parametrize(
    "content,named",
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "list"),
        ('{"beam_altitude_angles": [1, 2]}', "beam_azimuth_angles"),
        ('{"beam_altitude_angles": [1, 2], "beam_azimuth_angles": [0], "lidar_mode": "1024x10"}', "1 beam_azimuth"),
        ('{"beam_altitude_angles": [1, null], "beam_azimuth_angles": [0, 0], "lidar_mode": "1024x10"}', "None"),
        ('{"beam_altitude_angles": [1], "beam_azimuth_angles": [0]}', "columns_per_frame"),
        (
            '{"beam_altitude_angles": [1], "beam_azimuth_angles": [0], "lidar_mode": "512x10",'
            ' "lidar_to_sensor_transform": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}',
            "[2, 0, 0",
        ),
        # angles and shifts beyond any sensor's read silently (points in no direction the sensor has)
        ('{"beam_altitude_angles": [1, 1e11], "beam_azimuth_angles": [0, 0], "lidar_mode": "512x10"}', "s[1] is 1e+11"),
        ('{"beam_altitude_angles": [1, 2], "beam_azimuth_angles": [0, -1e308], "lidar_mode": "512x10"}', "+-180 deg"),
        (
            '{"beam_altitude_angles": [1, 2], "beam_azimuth_angles": [0, 0], "lidar_mode": "512x10",'
            ' "pixel_shift_by_row": [0, 99999999999]}',
            "pixel_shift_by_row[1] is 99999999999; a shift is a column offset of at most 8192",
        ),
    ],
)
def test_broken_ouster_metadata_is_refused(tmp_path, content, named):
    path = tmp_path / "meta.json"
    path.write_text(content)
    with pytest.raises(PatternError) as info:
        ouster(path)
    assert named in str(info.value)


def test_ouster_arguments_that_contradict_the_metadata():
    need(OUSTER_JSON)
    with pytest.raises(PatternError, match="beams=64"):
        ouster(OUSTER_JSON, beams=64)
    with pytest.raises(PatternError, match="columns=2048"):
        ouster(OUSTER_JSON, columns=2048)
