import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.io import read_kitti_bin, write_kitti_bin


def test_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    points = rng.normal(size=(100, 3)).astype(np.float32)
    intensity = rng.random(100).astype(np.float32)
    path = write_kitti_bin(tmp_path / "000000.bin", points, intensity)
    assert path.stat().st_size == 100 * 16
    records = read_kitti_bin(path)
    assert records.dtype == np.float32 and records.shape == (100, 4)
    np.testing.assert_array_equal(records[:, :3], points)
    np.testing.assert_array_equal(records[:, 3], intensity)
    np.testing.assert_array_equal(read_kitti_bin(write_kitti_bin(tmp_path / "b.bin", points))[:, 3], 0.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["000000.bin", "b.bin"]


def test_truncated_file_names_offset(tmp_path):
    path = tmp_path / "t.bin"
    path.write_bytes(np.zeros(9, "<f4").tobytes())
    with pytest.raises(LogFormatError, match="byte 32"):
        read_kitti_bin(path)
    with pytest.raises(LogFormatError, match="5-float32"):
        read_kitti_bin(write_kitti_bin(tmp_path / "k.bin", np.zeros((2, 3))), columns=5)
    with pytest.raises(ValueError, match="columns"):
        read_kitti_bin(path, columns=3)
