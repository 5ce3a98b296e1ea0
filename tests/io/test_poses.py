import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError, PoseError
from mi_lidar.io import read_any, read_kitti_poses, read_pose_matrices, read_poses, write_kitti_poses

from .synth import carmen_text


def _poses(n=5):
    angles = np.linspace(0, 2, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 0] = poses[:, 1, 1] = np.cos(angles)
    poses[:, 0, 1], poses[:, 1, 0] = -np.sin(angles), np.sin(angles)
    poses[:, :3, 3] = np.arange(3 * n).reshape(n, 3)
    return poses


def test_kitti_round_trip(tmp_path):
    poses = _poses()
    path = write_kitti_poses(tmp_path / "00.txt", poses)
    assert len(path.read_text().splitlines()) == 5
    assert all(len(line.split()) == 12 for line in path.read_text().splitlines())
    np.testing.assert_allclose(read_kitti_poses(path), poses, atol=1e-12)


def test_matrices_npy_and_text(tmp_path):
    poses = _poses(3)
    np.save(tmp_path / "p.npy", poses)
    np.testing.assert_array_equal(read_pose_matrices(tmp_path / "p.npy"), poses)
    np.savetxt(tmp_path / "p.txt", poses.reshape(3, 16))
    np.testing.assert_allclose(read_pose_matrices(tmp_path / "p.txt"), poses)


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (lambda p: p.__setitem__((2, 0, 3), np.nan), "pose 2 .*non-finite"),
        (lambda p: p.__setitem__((1, 0, 0), 1.1), "pose 1 .*orthonormal"),
        (lambda p: p.__setitem__((3, slice(0, 3), 0), -p[3, :3, 0]), "pose 3 .*determinant"),
        (lambda p: p.__setitem__((4, 3, 0), 0.5), r"pose 4 .*last row"),
        # a position of 1e12 m (a misread number) was taken
        (lambda p: p.__setitem__((1, 1, 3), -1e12), r"pose 1 has position y = -1e\+12 m, beyond 1e\+08 m \(farther"),
    ],
)
def test_invalid_pose_named(tmp_path, corrupt, message):
    poses = _poses()
    corrupt(poses)
    path = tmp_path / "bad.npy"
    np.save(path, poses)
    with pytest.raises(PoseError, match=f"bad.npy: {message}"):
        read_pose_matrices(path)


def test_a_carmen_pose_beyond_the_earth_is_refused(tmp_path):
    """x = 1e308 in a FLASER line read, and info printed a trajectory length of inf."""
    lines = carmen_text(3).splitlines()
    fields = lines[5].split()
    fields[-9] = "1e308"  # x of the laser pose (then y, theta, the odometry pose, the timestamps and host)
    (tmp_path / "far.log").write_text("\n".join([*lines[:5], " ".join(fields), *lines[6:]]) + "\n")
    with pytest.raises(PoseError, match=r"far.log: pose 1 has position x = 1e\+308 m, beyond 1e\+08 m"):
        read_any(tmp_path / "far.log")


def test_malformed_text(tmp_path):
    path = tmp_path / "p.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n")
    with pytest.raises(LogFormatError, match="line 2 has 3 numbers; expected 12"):
        read_kitti_poses(path)
    path.write_text("")
    with pytest.raises(LogFormatError, match="no poses"):
        read_kitti_poses(path)
    with pytest.raises(PoseError, match="pose 0"):
        write_kitti_poses(tmp_path / "o.txt", np.zeros((1, 4, 4)))
    assert not (tmp_path / "o.txt").exists()


def test_read_poses_takes_every_pose_file_and_a_saved_log(tmp_path):
    """`simulate --poses drive.npz` gave "'utf-8' codec can't decode byte ...": a log's poses are poses."""
    from mi_lidar.core.log import Log
    from mi_lidar.io import read_poses

    poses = _poses(3)
    write_kitti_poses(tmp_path / "k.txt", poses)
    np.save(tmp_path / "m.npy", poses)
    np.savetxt(tmp_path / "m.txt", poses.reshape(3, 16))
    for name in ("k.txt", "m.npy", "m.txt"):
        np.testing.assert_allclose(read_poses(tmp_path / name), poses, atol=1e-9)
    directions = np.tile(np.array([1.0, 0.0, 0.0]), (1, 2, 1, 1))
    ones = np.ones((3, 2, 1))
    log = Log(poses=poses, directions=directions, ranges=ones, hit=ones > 0, times=np.zeros((3, 2, 1)))
    np.testing.assert_allclose(read_poses(log.save(tmp_path / "drive.npz")), poses)
    (tmp_path / "junk.bin").write_bytes(b"\0\x89PNG" * 100)
    with pytest.raises(LogFormatError, match=r"junk\.bin: a binary file, not a pose file; give \.npy"):
        read_poses(tmp_path / "junk.bin")


@pytest.mark.parametrize(
    "text, message",
    [
        # read as a 16-number matrix file: 'line 1 has 1 numbers; expected 16'
        ("1,0,0,0,0,1,0,0,0,0,1,0\n", r"p.txt: line 1: numbers separated by commas; .* replace the commas by spaces"),
        # a file cut inside its last line: 'line 2 has 3 numbers; expected 12' without a word of why
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0", r"p.txt: line 2 has 3 numbers; expected 12 \(the file is cut short\?\)"),
        # a first line of 11 numbers (one dropped from a KITTI line) was read as a 4x4 file: 'expected 16'
        (
            "\n1 0 0 0 0 1 0 0 0 0 1\n",
            r"p.txt: line 2 has 11 numbers; a pose file has 12 \(KITTI: a 3x4 \[R \| t\]\) or 16",
        ),
    ],
)
def test_text_pose_files_say_what_is_wrong(tmp_path, text, message):
    (tmp_path / "p.txt").write_text(text)
    with pytest.raises(LogFormatError, match=message):
        read_poses(tmp_path / "p.txt")


def test_an_unreadable_kitti_pose_file_says_so(tmp_path, monkeypatch):
    """A bare PermissionError before (simulated: tests may run as root)."""
    import builtins

    path = write_kitti_poses(tmp_path / "p.txt", _poses())
    real_open = builtins.open

    def refuse(file, *args, **kwargs):
        if str(file) == str(path):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", refuse)
    with pytest.raises(LogFormatError, match=r"p.txt: cannot read the file \(permission denied\)"):
        read_kitti_poses(path)


def test_comment_lines_of_a_text_pose_file_are_skipped(tmp_path):
    """A header such as '# columns: r11 r12 ...' was read as a pose line: 'line 1 has 3 numbers'."""
    (tmp_path / "p.txt").write_text("# columns: r11 r12 r13 tx ...\n1 0 0 1 0 1 0 2 0 0 1 3\n  # end\n")
    np.testing.assert_allclose(read_poses(tmp_path / "p.txt")[0, :3, 3], [1, 2, 3])
