"""Bad files are refused by ``read_any`` (and so by every command that reads them) with a LogFormatError that
names the file and what to do: empty files, files cut short, random bytes, files of one format under another's
extension. Each case failed on the previous code with a reader's raw message (or read garbage as a scan)."""

import gzip
import re
import struct
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mi_lidar.cli import app
from mi_lidar.core.errors import LogFormatError, PoseError
from mi_lidar.io import (
    read_any,
    read_bin_log,
    read_las_log,
    read_ouster,
    read_pcd_log,
    read_ply_log,
    read_poses,
    write_any,
    write_kitti_poses,
    write_pcd_log,
    write_ply,
    write_ply_log,
)

from .synth import carmen_text, write_ouster
from .test_clouds import synthetic_log

# seed file -> (what the error calls such a file, the extension the fix names)
SIGNED = {
    "s.ply": ("a PLY point cloud", ".ply"),
    "s.las": ("a LAS/LAZ point cloud", ".las"),
    "log.npz": ("a zip archive", ".npz"),
    "s.exr": ("an OpenEXR image", ".exr"),
    "synth.pcap": ("a pcap capture", ".pcap"),
    "s.pcd": ("a PCD point cloud", ".pcd"),
    "poses.npy": ("a numpy .npy array", ".npy"),
}
REQUIRED = [name for name in SIGNED if name != "s.pcd"]  # a PCD may open with other comment lines
UNSIGNED = ("c.log", "k.bin")  # formats without a signature of their own
TARGETS = ("x.bin", "x.log", "x.npz", "x.ply", "x.pcd", "x.las", "x.exr", "x.pcap")


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("seeds")
    log = synthetic_log(height=4, width=16)
    for name in ("s.ply", "s.las", "s.exr", "s.pcd", "k.bin"):
        write_any(log, folder / name)
    write_ply_log(log, folder / "a.ply", binary=False)
    write_pcd_log(log, folder / "a.pcd", binary=False)
    synthetic_log(height=4, width=16, scans=2).save(folder / "log.npz")
    write_ouster(folder, np.full((8, 32), 5000, dtype=np.uint32))
    np.save(folder / "poses.npy", np.tile(np.eye(4), (2, 1, 1)))
    write_kitti_poses(folder / "poses.txt", np.tile(np.eye(4), (2, 1, 1)))
    (folder / "c.log").write_text(carmen_text(3))
    (folder / "c.log.gz").write_bytes(gzip.compress(carmen_text(3).encode()))
    return folder


def read(path):
    return read_poses(path) if path.suffix == ".npy" else read_any(path)


@pytest.mark.parametrize("name", [*SIGNED, *UNSIGNED, "c.log.gz", "n.pcd.bin"])
def test_an_empty_file_is_named_empty(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(LogFormatError, match=rf"{name}: empty file \(0 bytes\), not .*; re-create or copy it again"):
        read(path)


@pytest.mark.parametrize("name", REQUIRED)
@pytest.mark.parametrize("keep", [1, 3])
def test_a_file_cut_inside_its_signature_is_called_truncated(seeds, tmp_path, name, keep):
    path = tmp_path / name
    path.write_bytes((seeds / name).read_bytes()[:keep])
    with pytest.raises(LogFormatError, match=rf"{name}: {keep} byte\(s\), cut off inside the signature .*truncated"):
        read(path)


@pytest.mark.parametrize("name", REQUIRED)
def test_random_bytes_under_a_signed_extension_are_refused(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(7).integers(0, 256, 2000, dtype=np.uint8).tobytes())
    with pytest.raises(LogFormatError, match=rf"{name}: not .*: such a file starts with .*damaged, or another format"):
        read(path)


@pytest.mark.parametrize("source", [*SIGNED, "c.log.gz"])
@pytest.mark.parametrize("target", TARGETS)
def test_a_file_of_another_format_is_named_with_the_extension_to_give_it(seeds, tmp_path, source, target):
    """E.g. a PLY saved as scan.bin was read as 1e30 m points, a LAS as .npz said 'pickled (object) data'."""
    kind, suffix = SIGNED.get(source, ("a gzip file", ".log.gz"))
    if target.endswith(suffix) or (source == "c.log.gz" and target in ("x.log", "x.bin")):
        pytest.skip("the file's own format, or a 3-byte signature a float file matches by chance")
    path = tmp_path / target
    path.write_bytes((seeds / source).read_bytes())
    with pytest.raises(LogFormatError, match=rf"{target}: {re.escape(kind)}.* \(it starts with .*\), not .*{suffix}"):
        read(path)


def test_an_npz_under_npy_is_refused_not_a_traceback(seeds, tmp_path):
    """read_poses raised AttributeError ('NpzFile' object has no attribute 'ndim') for a log saved as .npy."""
    path = tmp_path / "poses.npy"
    path.write_bytes((seeds / "log.npz").read_bytes())
    with pytest.raises(LogFormatError, match=r"poses.npy: a zip archive .* rename it to .npz"):
        read_poses(path)


@pytest.mark.parametrize("dtype", ["U8", "complex128"])
def test_pose_arrays_of_text_or_complex_numbers_are_refused(tmp_path, dtype):
    """Strings were parsed and complex numbers silently lost their imaginary part."""
    path = tmp_path / "poses.npy"
    np.save(path, np.tile(np.eye(4), (2, 1, 1)).astype(dtype))
    with pytest.raises(LogFormatError, match=rf"poses.npy: array of {np.dtype(dtype)} values; expected real numbers"):
        read_poses(path)


def test_a_bag_folder_without_metadata_says_reindex(tmp_path):
    bag = write_any(synthetic_log(height=4, width=16, scans=2), tmp_path / "bag")
    (bag / "metadata.yaml").unlink()
    with pytest.raises(LogFormatError, match=r"bag: a ROS 2 bag folder without metadata.yaml .*ros2 bag reindex"):
        read_any(bag)


def test_a_bag_whose_metadata_is_not_yaml_is_one_line(tmp_path):
    """YAML's error came over seven lines, with a drawing of the spot, inside the one-line message."""
    bag = write_any(synthetic_log(height=4, width=16, scans=2), tmp_path / "bag")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 5\n")
    with pytest.raises(LogFormatError) as error:
        read_any(bag)
    message = str(error.value)
    assert "\n" not in message and "metadata.yaml: while parsing a flow mapping" in message, message
    assert message.endswith("the bag is damaged or incomplete: copy it again or record it again"), message


def deny(monkeypatch, path):
    """Make reading ``path`` raise PermissionError, as a chmod 000 file does (tests may run as root, whom chmod
    does not stop): through open, Path.read_bytes and numpy.fromfile."""
    import builtins

    def refuse(real):
        def call(file, *args, **kwargs):
            if str(file) == str(path):
                raise PermissionError(13, "Permission denied", str(file))
            return real(file, *args, **kwargs)

        return call

    monkeypatch.setattr(builtins, "open", refuse(builtins.open))
    monkeypatch.setattr(np, "fromfile", refuse(np.fromfile))
    monkeypatch.setattr(Path, "read_bytes", lambda self, real=Path.read_bytes: refuse(real)(self))


READERS = {  # the readers a user calls directly, by the seed they read
    "k.bin": read_bin_log,
    "s.ply": read_ply_log,
    "s.pcd": read_pcd_log,
    "s.las": read_las_log,
    "poses.npy": read_poses,
    "poses.txt": read_poses,
    "synth.pcap": lambda path: read_ouster(path, metadata=path.with_suffix(".json")),
}


@pytest.mark.parametrize("name", list(READERS))
def test_a_file_the_user_may_not_read_says_so(seeds, tmp_path, monkeypatch, name):
    """It was a bare PermissionError, which the CLI words as a fix for writing ('choose a folder you may write to')."""
    path = tmp_path / f"locked{Path(name).suffix}"
    path.write_bytes((seeds / name).read_bytes())
    if name == "synth.pcap":
        path.with_suffix(".json").write_bytes((seeds / "synth.json").read_bytes())
    deny(monkeypatch, path)
    with pytest.raises(LogFormatError, match=rf"{path.name}: cannot read the file \(permission denied\); .*chmod a\+r"):
        READERS[name](path)


def test_an_exr_the_user_may_not_read_says_so(seeds, tmp_path, monkeypatch):
    """OpenEXR opens the file itself and says only 'Unable to open ... for read'."""
    import mi_lidar.io.exr as exr

    path = tmp_path / "locked.exr"
    path.write_bytes((seeds / "s.exr").read_bytes())
    monkeypatch.setattr(exr.OpenEXR, "File", lambda *args, **kwargs: (_ for _ in ()).throw(RuntimeError("no")))
    monkeypatch.setattr(exr.os, "access", lambda *args: False)
    with pytest.raises(LogFormatError, match=r"locked.exr: cannot read the file \(permission denied\)"):
        exr.read_exr(path)


def test_a_bag_the_user_may_not_read_says_so(tmp_path, monkeypatch):
    """SQLite said 'unable to open database file', worded as 'the bag is damaged or incomplete: copy it again'."""
    import mi_lidar.io.rosbag as rosbag

    bag = write_any(synthetic_log(height=4, width=16, scans=2), tmp_path / "bag")
    storage = next(bag.glob("*.db3"))
    monkeypatch.setattr(rosbag.os, "access", lambda p, mode: Path(p) != storage)
    with pytest.raises(LogFormatError, match=rf"{storage.name}: cannot read the bag file \(permission denied\); make"):
        read_any(bag)


def test_a_damaged_exr_says_what_to_do(seeds, tmp_path):
    path = tmp_path / "cut.exr"
    path.write_bytes((seeds / "s.exr").read_bytes()[:-1])
    with pytest.raises(LogFormatError, match=r"cut.exr: not a readable EXR image .*damaged or cut short"):
        read_any(path)


@pytest.mark.parametrize("command", ["info", "convert"])
@pytest.mark.parametrize("source, target", [("s.ply", "scan.bin"), ("s.las", "scan.npz"), ("log.npz", "scan.exr")])
def test_the_commands_print_one_line_naming_the_file(seeds, tmp_path, command, source, target):
    path = tmp_path / target
    path.write_bytes((seeds / source).read_bytes())
    args = [command, str(path)] + ([str(tmp_path / "out.npz")] if command == "convert" else [])
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit), result.output
    (line,) = result.output.strip().splitlines()
    assert line.startswith("error: ") and target in line and "rename it to" in line
    assert not (tmp_path / "out.npz").exists()


def with_header(data: bytes, old: bytes, new: bytes) -> bytes:
    """``data`` with the first ``old`` of its header replaced by ``new``."""
    assert old in data[:2000]
    return data.replace(old, new, 1)


def las_count(data: bytes, count: int) -> bytes:
    """A LAS 1.4 file with its point count (legacy u32 at byte 107, u64 at 247) set to ``count``."""
    out = bytearray(data)
    struct.pack_into("<I", out, 107, count)
    struct.pack_into("<Q", out, 247, count)
    return bytes(out)


# a header counting fewer points than the data holds: the rest were dropped without a word
SHORT_COUNTS = {
    "ply-count": ("s.ply", lambda d: with_header(d, b"vertex 54", b"vertex 44"), r"260 bytes follow .*vertex 44'\)"),
    "ply-appended": ("s.ply", lambda d: d + d[-100:], r"100 bytes follow the data its header declares"),
    "ply-ascii-count": (
        "a.ply",
        lambda d: with_header(d, b"vertex 54", b"vertex 50"),
        r"378 values follow the header, which declares 350",
    ),
    "pcd-count": (
        "s.pcd",
        lambda d: with_header(with_header(d, b"WIDTH 16", b"WIDTH 12"), b"POINTS 64", b"POINTS 48"),
        r"416 bytes follow the data the header declares \(POINTS 48 x 26-byte records\)",
    ),
    "pcd-appended": ("s.pcd", lambda d: d + b"\x01" * 30, r"30 bytes follow the data"),
    "pcd-ascii-extra": ("a.pcd", lambda d: d + b"1 2 3 4 5 6 7\n", r"ascii data holds 455 values; .* promises 448"),
    "las-count": ("s.las", lambda d: las_count(d, 44), r"10 whole point records follow the point_count = 44"),
    "las-appended": ("s.las", lambda d: d + d[-80:], r"2 whole point records follow the point_count = 54"),
}


@pytest.mark.parametrize("case", list(SHORT_COUNTS))
def test_data_beyond_the_header_count_is_refused(seeds, tmp_path, case):
    seed, damage, message = SHORT_COUNTS[case]
    path = tmp_path / seed
    path.write_bytes(damage((seeds / seed).read_bytes()))
    with pytest.raises(LogFormatError, match=rf"{seed}: {message}.*correct the header or export"):
        read_any(path)


@pytest.mark.parametrize("seed", ["s.ply", "s.pcd"])
def test_a_trailing_newline_is_not_data(seeds, tmp_path, seed):
    path = tmp_path / seed
    path.write_bytes((seeds / seed).read_bytes() + b"\n")
    assert read_any(path).hit.sum() == read_any(seeds / seed).hit.sum()


def test_a_las_with_a_non_finite_scale_is_refused(seeds, tmp_path):
    """Every coordinate was NaN: the scan read as 54 misses."""
    data = bytearray((seeds / "s.las").read_bytes())
    struct.pack_into("<d", data, 131, float("nan"))
    (tmp_path / "s.las").write_bytes(bytes(data))
    with pytest.raises(LogFormatError, match=r"s.las: header fields scale \[nan, .*\] and offset .* must be finite"):
        read_any(tmp_path / "s.las")


def kitti_records(seeds) -> np.ndarray:
    return np.fromfile(seeds / "k.bin", dtype="<f4").reshape(-1, 4)


# a headerless .bin whose bytes are not float32 records of points: read as a scan of absurd points
NOT_RECORDS = {
    "random": (lambda r: np.random.default_rng(3).integers(0, 256, r.nbytes, dtype=np.uint8).tobytes(), "4-column"),
    "float64": (lambda r: r.astype("<f8").tobytes(), "4-column"),
    "text": (lambda r: b"hello world, this is not a scan\n" * 20, "4-column"),
}


@pytest.mark.parametrize("case", list(NOT_RECORDS))
def test_bytes_that_are_not_point_records_are_refused(seeds, tmp_path, case):
    make, columns = NOT_RECORDS[case]
    path = tmp_path / "k.bin"
    path.write_bytes(make(kitti_records(seeds)))
    with pytest.raises(LogFormatError, match=rf"k.bin: point \d+ has [xyz] = \S+ m, beyond 1e\+08 m: not {columns}"):
        read_any(path)


def test_a_bin_of_zero_bytes_is_refused(seeds, tmp_path):
    """It read as a scan of misses (a file allocated but never written)."""
    path = tmp_path / "k.bin"
    path.write_bytes(bytes(kitti_records(seeds).nbytes))
    with pytest.raises(LogFormatError, match=r"k.bin: all 864 bytes are zero, no point data"):
        read_any(path)


def test_non_finite_points_of_a_bin_are_misses(seeds, tmp_path):
    records = kitti_records(seeds).copy()
    records[:3, 0], records[3, 1] = np.nan, np.inf
    records.tofile(tmp_path / "k.bin")
    log = read_any(tmp_path / "k.bin")
    assert log.n_rays == len(records) and not log.hit[0, 0, :4].any() and log.hit[0, 0, 4:].all()


def test_a_nuscenes_ring_that_is_not_an_integer_is_named(tmp_path):
    records = np.zeros((8, 5), dtype="<f4")
    records[:, :3], records[:, 4] = 5.0, np.arange(8) % 2
    records[6, 4] = 2.5
    records.tofile(tmp_path / "n.pcd.bin")
    with pytest.raises(LogFormatError, match=r"n.pcd.bin: point 6 has ring \(column 5\) 2.5; ring ids are integers"):
        read_any(tmp_path / "n.pcd.bin")


def test_a_cloud_point_beyond_any_range_is_refused(tmp_path):
    """A flipped exponent in a PLY coordinate read as a return 1e30 m away."""
    points = np.full((10, 3), 2.0, dtype=np.float32)
    points[4, 1] = 1e30
    write_ply(tmp_path / "s.ply", points)
    with pytest.raises(LogFormatError, match=r"s.ply: point 4 has y = 1e\+30 m, beyond 1e\+08 m: a damaged file"):
        read_any(tmp_path / "s.ply")


def damaged_log(seeds, tmp_path, name: str, change) -> Path:
    """The seed log with one array changed by ``change(arrays)``, saved as ``name``."""
    arrays = dict(np.load(seeds / "log.npz"))
    change(arrays)
    np.savez(tmp_path / name, **arrays)
    return tmp_path / name


def set_value(key: str, index: tuple, value: float):
    def change(arrays):
        arrays[key] = arrays[key].copy()
        arrays[key][index] = value

    return change


# values no measurement has, in a log whose arrays have the right shapes: read without a word before
BAD_VALUES = {
    "nan-pose": (set_value("poses", (1, 0, 3), np.nan), PoseError, r"pose 1 is not a rigid transform: has non-finite"),
    "scaled-pose": (set_value("poses", (0, 0, 0), 2.0), PoseError, r"pose 0 is not a rigid transform: rotation"),
    "nan-time": (set_value("times", (1, 2, 3), np.nan), LogFormatError, r"ray \[1, 2, 3\] has time nan s"),
    "nan-direction": (set_value("directions", (0, 1, 2, 0), np.nan), LogFormatError, r"ray \[0, 1, 2\] has direction"),
    "long-direction": (
        lambda a: a.update(directions=a["directions"] * 3),
        LogFormatError,
        r"ray \[0, 0, 0\] has direction length 3.0 \(a unit vector has 1\)",
    ),
    "inf-origin": (
        set_value("origins", (0, 3, 1, 2), np.inf),
        LogFormatError,
        r"ray \[0, 3, 1\] has origin \[0.0, 0.0",
    ),
    "negative-range": (
        lambda a: a.update(ranges=np.where(a["hit"], -1.5, a["ranges"])),
        LogFormatError,
        r"ray \[0, 0, \d+\] has range of a hit -1.5 m \(ranges are >= 0\)",
    ),
    # a hit 1e30 m away, and times in nanoseconds read as seconds (info: 'time span (s) 10000000150474662198...')
    "far-range": (
        lambda a: a.update(ranges=np.where(a["hit"], 1e30, a["ranges"])),
        LogFormatError,
        r"ray \[0, 0, \d+\] has range of a hit 1\.0\d*e\+30 m, beyond 1e\+08 m",
    ),
    "ns-time": (
        lambda a: a.update(times=a["times"] * 1e10),
        LogFormatError,
        r"ray \[0, 0, 0\] has time 1000000000000.0 s, beyond 1e\+11 s from 1970 \(ms, us or ns\?\)",
    ),
}


@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_a_log_with_values_no_measurement_has_is_refused(seeds, tmp_path, case):
    change, error, message = BAD_VALUES[case]
    path = damaged_log(seeds, tmp_path, "log.npz", change)
    with pytest.raises(error, match=rf"log.npz: {message}"):
        read_any(path)


def test_compare_names_the_log_with_a_nan_direction(tmp_path):
    """compare plotted it and failed with matplotlib's \"'x' must be finite, check for nan or inf values\"."""
    import mi_lidar
    from tests.conftest import SCENES

    log = mi_lidar.simulate(mi_lidar.load_scene(SCENES / "indoor_planar.xml"), seed=1)
    log.directions = log.directions.copy()
    log.directions[0, 7, 0] = np.nan
    path = log.save(tmp_path / "room.npz")
    result = CliRunner().invoke(app, ["compare", str(path), str(SCENES / "indoor_planar.xml"), "--out", str(tmp_path)])
    assert result.exit_code == 2, result.output
    assert "room.npz: ray [0, 7, 0] has direction length nan" in result.output.replace("\n", "")


def bag_counting(tmp_path, count: str) -> Path:
    """A bag of two clouds on /points whose metadata.yaml counts ``count`` messages on that topic."""
    bag = write_any(synthetic_log(height=4, width=16, scans=2), tmp_path / "bag")
    meta = bag / "metadata.yaml"
    pattern = r"message_count: 2(\n\s+topic_metadata:\n\s+name: /points)"
    meta.write_text(re.sub(pattern, rf"message_count: {count}\1", meta.read_text()))
    return bag


def test_a_bag_missing_messages_its_metadata_counts_is_refused(tmp_path):
    """A storage file holding 2 of the 20 clouds metadata.yaml counts read as a 2-scan log."""
    with pytest.raises(LogFormatError, match=r"bag: its metadata counts 20 messages on /points, its storage holds 2"):
        read_any(bag_counting(tmp_path, "20"))


@pytest.mark.parametrize("count", ["nan", "-3", "2.5", "null"])
def test_a_bag_whose_metadata_count_is_not_a_count_is_refused(tmp_path, count):
    """A message_count of 'nan' in metadata.yaml raised TypeError (unsupported operand type(s) for +)."""
    with pytest.raises(LogFormatError, match=r"bag: its metadata counts .* messages on /points; a message_count is a "):
        read_any(bag_counting(tmp_path, count))


def test_a_damaged_bag_says_what_to_do(tmp_path):
    bag = write_any(synthetic_log(height=4, width=16, scans=2), tmp_path / "bag")
    storage = next(bag.glob("*.db3"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    with pytest.raises(LogFormatError, match=r"bag: not a readable ROS bag .*; the bag is damaged or incomplete: copy"):
        read_any(bag)


def test_a_cut_exr_says_the_library_reason_once_and_prints_nothing(seeds, tmp_path, capfd):
    """OpenEXR printed 'Warning: Exception raised reading pixel data ...' and '(EXR_ERR_BAD_CHUNK_LEADER) ...'
    around the error line, which said only 'Invalid part index '0': file has 0 parts.'."""
    data = (seeds / "s.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    capfd.readouterr()
    with pytest.raises(LogFormatError, match=r"cut.exr: not a readable EXR image \(\(EXR_ERR_BAD_CHUNK_LEADER\) .*"):
        read_any(tmp_path / "cut.exr")
    assert capfd.readouterr() == ("", "")
    print("descriptors restored")
    assert capfd.readouterr().out == "descriptors restored\n"


def test_reading_warns_nothing(seeds, tmp_path):
    """Random bytes under .bin printed numpy's 'invalid value encountered in reduce' (a signalling NaN) after the
    error; a planar scan saved as PLY printed two 'invalid value encountered in divide' (corrcoef of equal ring
    elevations) before info's table."""
    import warnings

    (tmp_path / "k.bin").write_bytes(np.random.default_rng(3).integers(0, 256, 864, dtype=np.uint8).tobytes())
    planar = write_any(read_any(seeds / "c.log").scan(1), tmp_path / "planar.ply")  # hits only: 179 of 180 beams
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(LogFormatError, match="k.bin: point"):
            read_any(tmp_path / "k.bin")
        log = read_any(planar)
    assert log.shape == (1, 180, 1) and log.attributes["valid"].sum() == 179
