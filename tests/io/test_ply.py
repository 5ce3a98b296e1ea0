import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.io import read_ply, write_ply


@pytest.mark.parametrize("binary", [True, False])
def test_round_trip_preserves_values_and_dtypes(tmp_path, binary):
    rng = np.random.default_rng(1)
    points = rng.normal(size=(500, 3)).astype(np.float32)
    attributes = {
        "intensity": rng.random(500).astype(np.float32),
        "ring": rng.integers(0, 32, 500).astype(np.uint16),
        "label": rng.integers(-5, 5, 500).astype(np.int32),
        "t": rng.random(500),
    }
    path = write_ply(tmp_path / "c.ply", points, attributes, binary=binary)
    back_points, back = read_ply(path)
    assert back_points.dtype == np.float32
    np.testing.assert_array_equal(back_points, points)
    assert set(back) == set(attributes)
    for name, values in attributes.items():
        assert back[name].dtype == values.dtype, name
        np.testing.assert_array_equal(back[name], values)


def test_wide_and_bool_attributes_are_narrowed(tmp_path):
    points = np.zeros((3, 3))
    _, back = read_ply(
        write_ply(tmp_path / "c.ply", points, {"id": np.array([1, 2, 3]), "hit": np.array([1, 0, 1], bool)})
    )
    assert back["id"].dtype == np.int32 and back["hit"].dtype == np.uint8
    np.testing.assert_array_equal(back["id"], [1, 2, 3])
    with pytest.raises(ValueError, match="exceed"):
        write_ply(tmp_path / "d.ply", points, {"id": np.array([1, 2, 2**40])})
    with pytest.raises(ValueError, match="shape"):
        write_ply(tmp_path / "d.ply", points, {"id": np.array([1, 2])})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.ply"]


def test_read_errors(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n\x00")
    with pytest.raises(LogFormatError, match="bad.ply"):
        read_ply(bad)
    no_vertex = tmp_path / "face.ply"
    no_vertex.write_bytes(b"ply\nformat ascii 1.0\nelement face 0\nproperty float a\nend_header\n")
    with pytest.raises(LogFormatError, match="vertex"):
        read_ply(no_vertex)
    with pytest.raises(LogFormatError, match="no such"):
        read_ply(tmp_path / "missing.ply")
