"""The log data model and its on-disk format."""

import json
import math

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from tests.core.test_strict_json import strict_load


def small_log(scans=2):
    rng = np.random.default_rng(0)
    h, w = 3, 5
    d = rng.normal(size=(1, h, w, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    ranges = rng.uniform(1, 10, (scans, h, w)).astype(np.float32)
    hit = rng.random((scans, h, w)) > 0.3
    ranges[~hit] = np.nan
    return Log(
        poses=np.stack([np.eye(4)] * scans),
        directions=d,
        ranges=ranges,
        hit=hit,
        times=np.zeros((scans, h, w)),
        attributes={"label": rng.integers(0, 4, (scans, h, w)).astype(np.int32)},
        sensor={"pattern": "test"},
    )


def test_round_trip_is_exact(tmp_path):
    log = small_log()
    back = Log.load(log.save(tmp_path / "a.npz"))
    np.testing.assert_array_equal(back.ranges, log.ranges)
    np.testing.assert_array_equal(back.hit, log.hit)
    np.testing.assert_array_equal(back.attributes["label"], log.attributes["label"])
    assert back.sensor == {"pattern": "test"}
    assert [p.name for p in tmp_path.iterdir()] == ["a.npz"]  # no temporary file left


def test_non_finite_sensor_values_read_back_and_the_header_is_strict_json(tmp_path):
    """A sensor without a far end (max_range inf), a CARMEN log without a no-return value (max_range_m inf): the
    header held ``Infinity``, which is not JSON; now null, listed so that the log reads back as it was."""
    log = small_log()
    log.sensor = {"pattern": "test", "max_range": math.inf, "max_range_m": math.inf, "offset": -math.inf}
    log.sensor |= {"figures": [1.5, math.nan], "calibration": None}
    path = log.save(tmp_path / "a.npz")
    with np.load(path) as data:
        header = strict_load(data["meta"].tobytes().decode())
    assert header["sensor"]["max_range"] is None and header["sensor"]["figures"] == [1.5, None]
    back = Log.load(path)
    assert json.dumps(back.sensor) == json.dumps(log.sensor)  # Python's json writes NaN: NaN compares too
    assert back.sensor["max_range"] == math.inf and back.sensor["offset"] == -math.inf


def test_points_put_misses_at_nan_and_hits_on_the_ray():
    log = small_log(1)
    points = log.points_sensor()
    assert np.isnan(points[~log.hit]).all()
    np.testing.assert_allclose(np.linalg.norm(points[log.hit], axis=-1), log.ranges[log.hit], rtol=1e-5)


def test_truncated_file_is_a_clean_error(tmp_path):
    path = small_log().save(tmp_path / "a.npz")
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(LogFormatError, match="truncated"):
        Log.load(path)


def test_mismatched_shapes_are_named():
    log = small_log()
    with pytest.raises(LogFormatError, match="hit has shape"):
        Log(poses=log.poses, directions=log.directions, ranges=log.ranges, hit=log.hit[:1], times=log.times)


def test_hit_with_nan_range_is_rejected():
    log = small_log(1)
    hit = np.ones_like(log.hit)
    with pytest.raises(LogFormatError, match="non-finite range"):
        Log(poses=log.poses, directions=log.directions, ranges=log.ranges, hit=hit, times=log.times)


def test_wrong_version(tmp_path):
    import json

    log = small_log()
    path = log.save(tmp_path / "a.npz")
    with np.load(path) as data:
        arrays = dict(data)
    arrays["meta"] = np.frombuffer(json.dumps({"format": "mi-lidar-log", "version": 99}).encode(), np.uint8)
    np.savez(path, **arrays)
    with pytest.raises(LogFormatError, match="version 99"):
        Log.load(path)


def test_three_dimensional_directions_get_default_origins():
    log = small_log(1)
    plain = Log(poses=log.poses, directions=log.directions[0], ranges=log.ranges, hit=log.hit, times=log.times)
    assert plain.origins.shape == (1, 3, 5, 3) and not plain.origins.any()


def test_select_keeps_the_chosen_scans_in_order():
    log = small_log(scans=4)
    for scans, expected in ((slice(1, None, 2), [1, 3]), ([2, 0], [2, 0])):
        part = log.select(scans)
        assert part.n_scans == len(expected)
        np.testing.assert_array_equal(part.ranges, log.ranges[expected])
        np.testing.assert_array_equal(part.attributes["label"], log.attributes["label"][expected])
        assert part.directions.shape[0] == 1 and part.sensor == log.sensor
    np.testing.assert_array_equal(log.scan(2).hit, log.hit[2:3])


def test_load_refuses_values_no_measurement_has(tmp_path):
    """Log.load read a NaN pose or a negative hit range silently (only read_any checked the values)."""
    from mi_lidar.core.errors import PoseError

    log = small_log()
    log.poses[1, 0, 3] = np.nan
    with pytest.raises(PoseError, match=r"nan.npz: pose 1 is not a rigid transform: has non-finite"):
        Log.load(log.save(tmp_path / "nan.npz"))
    log = small_log()
    log.ranges[log.hit] = -2.0
    with pytest.raises(LogFormatError, match=r"neg.npz: ray \[0, 0, \d\] has range of a hit -2.0 m"):
        Log.load(log.save(tmp_path / "neg.npz"))


def test_check_values_names_the_source():
    log = small_log()
    log.times[0, 1, 2] = np.inf
    with pytest.raises(LogFormatError, match=r"^scan A: ray \[0, 1, 2\] has time inf s"):
        log.check_values("scan A")
