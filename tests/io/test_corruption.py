"""Property-based robustness: every reader turns damaged input into a clean LogFormatError."""

import gzip
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.io import (
    read_bin_log,
    read_carmen,
    read_exr_log,
    read_las_log,
    read_ouster,
    read_pcd_log,
    read_ply_log,
    read_rosbag_log,
    read_velodyne,
    write_any,
    write_pcd,
)

from .synth import carmen_text, pcap_bytes, velodyne_payloads, write_ouster
from .test_clouds import synthetic_log

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@st.composite
def corruptions(draw, size: int):
    """A function damaging a byte string: truncation, byte flips, garbage splice or appended junk."""
    kind = draw(st.sampled_from(["truncate", "flip", "garbage", "append"]))
    if kind == "truncate":
        cut = draw(st.integers(0, max(size - 1, 0)))
        return lambda data: data[:cut]
    if kind == "flip":
        positions = draw(st.lists(st.integers(0, size - 1), min_size=1, max_size=8))
        masks = draw(st.lists(st.integers(1, 255), min_size=len(positions), max_size=len(positions)))

        def flip(data):
            out = bytearray(data)
            for position, mask in zip(positions, masks):
                out[position] ^= mask
            return bytes(out)

        return flip
    if kind == "garbage":
        start = draw(st.integers(0, size - 1))
        junk = draw(st.binary(min_size=1, max_size=64))
        return lambda data: data[:start] + junk + data[start + len(junk) :]
    junk = draw(st.binary(min_size=1, max_size=64))
    return lambda data: data + junk


def _seeds(folder: Path) -> dict:
    """name -> (file to damage, reader taking the damaged path)."""
    seeds = {}
    ouster = write_ouster(folder, np.random.default_rng(0).integers(0, 9000, (8, 32)).astype(np.uint32))
    seeds["ouster-pcap"] = (ouster, lambda p: read_ouster(p, metadata=ouster.with_suffix(".json")))
    seeds["ouster-json"] = (ouster.with_suffix(".json"), lambda p: read_ouster(ouster, metadata=p))
    azimuth = np.arange(36).reshape(3, 12) * 40.0
    distances = np.random.default_rng(1).integers(0, 3000, (3, 12, 32))
    velodyne = folder / "v.pcap"
    velodyne.write_bytes(pcap_bytes(velodyne_payloads(distances, azimuth), 2368, step=1327.104e-6))
    seeds["velodyne-pcap"] = (velodyne, read_velodyne)
    calibration = folder / "v.yaml"
    calibration.write_text(
        "lasers:\n"
        + "".join(
            f"- {{laser_id: {i}, rot_correction: 0.0, vert_correction: {np.radians(2 * i - 15):.6f}}}\n"
            for i in range(16)
        )
    )
    seeds["velodyne-yaml"] = (calibration, lambda p: read_velodyne(velodyne, calibration=p))
    (folder / "c.log").write_text(carmen_text(3))
    seeds["carmen"] = (folder / "c.log", read_carmen)
    (folder / "c.log.gz").write_bytes(gzip.compress(carmen_text(3).encode()))
    seeds["carmen-gz"] = (folder / "c.log.gz", read_carmen)
    log = synthetic_log(height=4, width=16)
    records = np.concatenate([np.random.default_rng(2).normal(size=(64, 4)), np.tile(np.arange(4), 16)[:, None]], 1)
    records.astype("<f4").tofile(folder / "n.pcd.bin")
    seeds["nuscenes-bin"] = (folder / "n.pcd.bin", read_bin_log)
    for suffix, reader in (
        (".ply", read_ply_log),
        (".pcd", read_pcd_log),
        (".las", read_las_log),
        (".exr", read_exr_log),
    ):
        seeds[suffix[1:]] = (write_any(log, folder / f"s{suffix}"), reader)
    cloud = {c: np.arange(20, dtype=np.float32) + i for i, c in enumerate("xyz")}
    seeds["pcd-ascii"] = (write_pcd(folder / "a.pcd", cloud, binary=False), read_pcd_log)
    bag = write_any(log, folder / "bag")
    seeds["rosbag"] = (next(bag.glob("*.db3")), read_rosbag_log)
    return seeds


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return _seeds(tmp_path_factory.mktemp("seeds"))


SEED_NAMES = [
    "ouster-pcap",
    "ouster-json",
    "velodyne-pcap",
    "velodyne-yaml",
    "carmen",
    "carmen-gz",
    "nuscenes-bin",
    "ply",
    "pcd",
    "las",
    "exr",
    "pcd-ascii",
    "rosbag",
]


def test_seeds_read_cleanly(seeds):
    assert sorted(seeds) == sorted(SEED_NAMES)
    for name, (path, reader) in seeds.items():
        assert isinstance(reader(path), Log), name


@pytest.mark.parametrize("name", SEED_NAMES)
def test_damaged_files_raise_log_format_error(seeds, name):
    path, reader = seeds[name]
    original = path.read_bytes()

    @FUZZ
    @given(damage=corruptions(len(original)))
    def check(damage):
        with tempfile.TemporaryDirectory() as folder:
            if name == "rosbag":
                target = Path(folder) / "bag"
                shutil.copytree(path.parent, target)
                target = target / path.name
            else:
                target = Path(folder) / path.name
            target.write_bytes(damage(original))
            try:
                result = reader(target.parent if name == "rosbag" else target)
            except LogFormatError as exc:
                assert str(exc)
            else:
                assert isinstance(result, Log)

    check()


def test_empty_files_are_reported(seeds, tmp_path):
    for name, (path, reader) in seeds.items():
        if name == "rosbag":
            continue
        empty = tmp_path / path.name
        empty.write_bytes(b"")
        with pytest.raises(LogFormatError):
            reader(empty)
