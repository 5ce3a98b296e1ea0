import json
import math
import os
import re

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.io import read_any, read_exr, write_any, write_exr
from tests.core.test_strict_json import strict_load

from .test_clouds import synthetic_log


def test_round_trip_is_exact_and_looked_up_by_name(tmp_path):
    rng = np.random.default_rng(0)
    ranges = rng.uniform(0.1, 120.0, (32, 1024)).astype(np.float32)
    ranges[3, 5] = np.nan
    element = rng.integers(0, 2**32 - 1, (32, 1024), dtype=np.uint32)
    channels = {"range": ranges, "element_id": element, "B": ranges * 2, "R": ranges + 1}
    path = write_exr(tmp_path / "scan.exr", channels)
    back = read_exr(path)
    assert set(back) == set(channels)
    np.testing.assert_array_equal(back["range"], ranges)
    assert back["range"].dtype == np.float32
    np.testing.assert_array_equal(back["element_id"], element)
    assert back["element_id"].dtype == np.uint32
    np.testing.assert_array_equal(back["R"], ranges + 1)
    np.testing.assert_array_equal(back["B"], ranges * 2)


def test_float64_stored_as_float32_and_signed_int_as_float(tmp_path):
    values = np.linspace(0, 1, 12, dtype=np.float64).reshape(3, 4)
    labels = np.arange(-6, 6).reshape(3, 4)
    mask = values > 0.5
    back = read_exr(write_exr(tmp_path / "a.exr", {"v": values, "label": labels, "hit": mask}))
    np.testing.assert_array_equal(back["v"], values.astype(np.float32))
    np.testing.assert_array_equal(back["label"], labels.astype(np.float32))
    np.testing.assert_array_equal(back["hit"], mask.astype(np.uint32))


def test_write_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        write_exr(tmp_path / "a.exr", {"a": np.zeros((2, 3)), "b": np.zeros((3, 2))})
    with pytest.raises(ValueError, match="exactly"):
        write_exr(tmp_path / "a.exr", {"a": np.array([[-1, 2**30]])})
    with pytest.raises(ValueError, match="at least one"):
        write_exr(tmp_path / "a.exr", {})
    assert list(tmp_path.iterdir()) == []


def test_non_finite_sensor_values_read_back_and_the_header_is_strict_json(tmp_path):
    """The mi_lidar_sensor header attribute held ``Infinity`` for a sensor without a far end: not JSON."""
    log = synthetic_log()
    log.sensor = {"name": "synthetic", "max_range": math.inf, "figures": [math.nan, 2.0]}
    path = write_any(log, tmp_path / "scan.exr")
    _, metadata = read_exr(path, with_metadata=True)
    assert strict_load(metadata["mi_lidar_sensor"])["max_range"] is None
    strict_load(metadata["mi_lidar_pose"])
    back = read_any(path).sensor
    assert back.pop("source") == str(path)
    assert json.dumps(back) == json.dumps(log.sensor)  # Python's json writes NaN: NaN compares too


def test_atomic_write_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "scan.exr"
    write_exr(path, {"range": np.ones((2, 3), np.float32)})
    write_exr(path, {"range": np.full((2, 3), 2.0, np.float32)})
    assert [p.name for p in tmp_path.iterdir()] == ["scan.exr"]
    np.testing.assert_array_equal(read_exr(path)["range"], 2.0)
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_read_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr at all")
    with pytest.raises(LogFormatError, match="bad.exr"):
        read_exr(bad)
    with pytest.raises(LogFormatError, match="no such"):
        read_exr(tmp_path / "missing.exr")
    good = write_exr(tmp_path / "good.exr", {"range": np.ones((64, 64), np.float32)})
    truncated = tmp_path / "trunc.exr"
    truncated.write_bytes(good.read_bytes()[:200])
    with pytest.raises(LogFormatError, match="trunc.exr"):
        read_exr(truncated)


@pytest.mark.parametrize("channel, value, allowed", [("elevation", 7.0, "pi/2"), ("azimuth", 1e30, "pi")])
def test_a_range_image_with_an_angle_beyond_its_range_is_refused(tmp_path, channel, value, allowed):
    """An elevation of 7 rad or an azimuth of 1e30 rad read silently: cos and sin gave some unit direction."""
    channels, metadata = read_exr(write_any(synthetic_log(height=4, width=16), tmp_path / "s.exr"), with_metadata=True)
    channels[channel][2, 5] = value
    write_exr(tmp_path / "bad.exr", channels, metadata)
    said = f"bad.exr: channel '{channel}' at pixel [2, 5] is {value:g} rad; range images hold {channel} angles"
    with pytest.raises(LogFormatError, match=re.escape(f"{said} within +-{allowed} rad")):
        read_any(tmp_path / "bad.exr")
