import warnings

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError, TruncatedLogWarning
from mi_lidar.io import read_any, read_velodyne
from mi_lidar.io.velodyne import MODELS

from .conftest import data_file
from .synth import pcap_bytes, velodyne_payloads

PACKET_US = {"VLP-16": 12 * 110.592, "HDL-32E": 12 * 46.08, "VLP-32C": 12 * 55.296}
STEP_CDEG = {"VLP-16": 39.81, "HDL-32E": 16.59, "VLP-32C": 19.91}


def _capture(tmp_path, model="VLP-16", packets=10, start_cdeg=0.0, distance=2500, mode=0x37, product=0x22):
    blocks = 6 if mode == 0x39 else 12
    step = STEP_CDEG[model] * (2 if mode == 0x39 else 1)
    azimuth = start_cdeg + step * np.arange(packets * blocks).reshape(packets, blocks)
    if mode == 0x39:
        azimuth = np.repeat(azimuth, 2, axis=1)
    distances = np.broadcast_to(np.asarray(distance), (packets, 12, 32))
    packet_us = PACKET_US[model] / (2 if mode == 0x39 else 1)
    payloads = velodyne_payloads(distances, np.round(azimuth), mode=mode, product=product, packet_us=packet_us)
    path = tmp_path / f"{model}.pcap"
    path.write_bytes(pcap_bytes(payloads, 2368, step=packet_us * 1e-6))
    return path


def test_real_vlp16_capture():
    log = read_velodyne(data_file("velodyne/velodyne_vlp16.pcap"), data_file("velodyne/VLP16db.yaml"))
    assert log.shape == (2, 16, 1464)
    assert log.sensor["columns_per_scan"] == [552, 1464]
    valid = log.attributes["valid"]
    assert valid.sum() == 16 * 84 * 24
    assert abs((1 - log.hit[valid].mean()) - 0.393) < 0.002
    assert not log.hit[~valid].any()
    elevation = np.degrees(np.arcsin(log.directions[0, :, 0, 2]))
    np.testing.assert_allclose(elevation, np.arange(15, -16, -2), atol=1e-4)
    np.testing.assert_array_equal(
        log.attributes["laser_id"][0, :, 0], [15, 13, 11, 9, 7, 5, 3, 1, 14, 12, 10, 8, 6, 4, 2, 0]
    )
    assert 2.0 < np.nanmin(log.ranges) and np.nanmax(log.ranges) < 131.0
    assert np.all(np.diff(log.times[1, 0, :1464]) > 0)
    # Cutting at the first azimuth makes the first frame one complete revolution.
    full = read_velodyne(
        data_file("velodyne/velodyne_vlp16.pcap"), data_file("velodyne/VLP16db.yaml"), cut_azimuth_deg=None
    )
    assert full.sensor["columns_per_scan"][0] == 1811
    azimuth = np.degrees(np.unwrap(np.arctan2(full.directions[0, 7, :1811, 1], full.directions[0, 7, :1811, 0])))
    assert 359.0 < abs(azimuth[-1] - azimuth[0]) < 360.0


@pytest.mark.parametrize("model, product", [("VLP-16", 0x22), ("HDL-32E", 0x21), ("VLP-32C", 0x28)])
def test_models_from_product_byte(tmp_path, model, product):
    log = read_velodyne(_capture(tmp_path, model, product=product))
    spec = MODELS[model]
    assert log.sensor["name"] == f"velodyne:{model}"
    assert log.shape[1] == spec.lasers
    assert log.shape[2] == 10 * 12 * spec.sequences_per_block
    np.testing.assert_allclose(log.ranges[log.hit], 2500 * spec.resolution_m, rtol=1e-6)
    elevation = np.degrees(np.arcsin(log.directions[0, :, 0, 2]))
    np.testing.assert_allclose(elevation, np.sort(spec.elevation_deg)[::-1], atol=1e-4)


def test_point_geometry_follows_ros_convention(tmp_path):
    log = read_velodyne(_capture(tmp_path, "HDL-32E", start_cdeg=9000, distance=5000, product=0x21))
    row = int(np.argmin(np.abs(np.degrees(np.arcsin(log.directions[0, :, 0, 2])))))
    point = log.points_sensor()[0, row, 0]
    np.testing.assert_allclose(point[1], -10.0, atol=1e-4)
    assert abs(point[0]) < 0.02 and abs(point[2]) < 1e-3
    assert log.attributes["laser_id"][0, row, 0] == 15


def test_dual_returns(tmp_path):
    distance = np.zeros((12, 32))
    distance[0::2], distance[1::2] = 1000, 2000
    path = _capture(tmp_path, distance=distance, mode=0x39)
    strongest = read_velodyne(path)
    assert strongest.shape == (1, 16, 10 * 6 * 2)
    assert np.all(strongest.ranges == np.float32(4.0))
    np.testing.assert_allclose(strongest.attributes["range_last"], 2.0)
    last = read_velodyne(path, return_mode="last")
    assert np.all(last.ranges == np.float32(2.0))
    np.testing.assert_allclose(last.attributes["range_strongest"], 4.0)


def test_frames_split_at_azimuth_wrap(tmp_path):
    log = read_velodyne(_capture(tmp_path, packets=20, start_cdeg=33000))
    counts = log.sensor["columns_per_scan"]
    assert len(counts) == 2 and sum(counts) == 20 * 24
    assert abs(counts[0] - 3000 / 20) <= 2
    assert not log.attributes["valid"][0, :, counts[0] :].any()


def test_mismatched_model_or_calibration(tmp_path):
    path = _capture(tmp_path)
    with pytest.raises(LogFormatError, match=r"1327\.\d us apart but a HDL-32E in strongest mode sends one every 553"):
        read_velodyne(path, model="HDL-32E")
    table = "lasers:\n" + "".join(
        f"- {{laser_id: {i}, rot_correction: 0.0, vert_correction: {np.radians(i - 16):.6f}}}\n" for i in range(32)
    )
    (tmp_path / "32.yaml").write_text(table)
    with pytest.raises(LogFormatError, match=r"32\.yaml has 32 lasers but a VLP-16 \(model='VLP-16'\) has 16"):
        read_velodyne(path, tmp_path / "32.yaml", model="VLP-16")
    (tmp_path / "bad.yaml").write_text("lasers:\n- {laser_id: 0}\n")
    with pytest.raises(LogFormatError, match=r"lasers\[0\]: bad or missing field"):
        read_velodyne(path, tmp_path / "bad.yaml")
    (tmp_path / "other.pcap").write_bytes(pcap_bytes([bytes(100)], 2368))
    with pytest.raises(LogFormatError, match="no 1206-byte Velodyne data packets"):
        read_velodyne(tmp_path / "other.pcap")


def _table(tmp_path, model: str, resolution: float | None = None, name: str = "table.yaml"):
    """A calibration YAML with ``model``'s nominal elevations (+0.1 deg, as a per-unit correction)."""
    lines = [f"distance_resolution: {resolution}"] if resolution else []
    lines += ["lasers:"] + [
        f"- {{laser_id: {i}, rot_correction: 0.0, vert_correction: {np.radians(e + 0.1):.6f}}}"
        for i, e in enumerate(MODELS[model].elevation_deg)
    ]
    (tmp_path / name).write_text("\n".join(lines) + "\n")
    return tmp_path / name


def test_table_of_another_model_is_an_error(tmp_path):
    hdl = _capture(tmp_path, "HDL-32E", product=0x21)
    vlp32 = _table(tmp_path, "VLP-32C", 0.004)
    with pytest.raises(LogFormatError, match=r"holds the elevations of a VLP-32C but the packets' product byte 0x21"):
        read_velodyne(hdl, calibration=vlp32)
    own = _table(tmp_path, "HDL-32E", 0.004, "hdl.yaml")
    with pytest.raises(LogFormatError, match=r"distance_resolution 0\.004 m .* \(ranges would scale by 2\)"):
        read_velodyne(hdl, calibration=own)
    log = read_velodyne(hdl, calibration=_table(tmp_path, "HDL-32E", 0.002, "hdl2.yaml"))
    np.testing.assert_allclose(log.ranges[log.hit], 2500 * 0.002, rtol=1e-6)


def test_model_from_timing_or_table_when_the_product_byte_is_wrong_or_unknown(tmp_path):
    vlp16 = read_velodyne(_capture(tmp_path, "VLP-16", product=0x21))  # HDL-32E byte, VLP-16 timing
    assert vlp16.sensor["name"] == "velodyne:VLP-16" and "packet spacing" in vlp16.sensor["model_source"]
    unknown = _capture(tmp_path, "VLP-32C", product=0x00)
    log = read_velodyne(unknown, calibration=_table(tmp_path, "VLP-32C"))
    assert log.sensor["name"] == "velodyne:VLP-32C" and "table.yaml" in log.sensor["model_source"]
    np.testing.assert_allclose(log.ranges[log.hit], 2500 * 0.004, rtol=1e-6)
    with pytest.raises(LogFormatError, match=r"663\.\d us apart but a HDL-32E in strongest mode sends one every 553"):
        read_velodyne(unknown, calibration=_table(tmp_path, "VLP-32C"), model="HDL-32E")


def test_dispatch_reads_velodyne_pcap(tmp_path):
    assert read_any(_capture(tmp_path)).sensor["name"] == "velodyne:VLP-16"


def test_cli_model_and_calibration_options(tmp_path):
    from typer.testing import CliRunner

    from mi_lidar.cli import app

    runner = CliRunner()
    hdl = _capture(tmp_path, "HDL-32E", product=0x21)
    (tmp_path / "tables").mkdir()
    vlp32 = _table(tmp_path / "tables", "VLP-32C", 0.004)
    result = runner.invoke(app, ["info", str(hdl), "--calibration", str(vlp32)])
    assert result.exit_code == 2
    assert "holds the elevations of a VLP-32C" in " ".join(result.output.split())
    result = runner.invoke(app, ["info", str(hdl), "--model", "VLP-16"])
    assert result.exit_code == 2 and "VLP-16 in strongest mode" in " ".join(result.output.split())
    result = runner.invoke(app, ["convert", str(hdl), str(tmp_path / "hdl.npz"), "--model", "HDL-32E"])
    assert result.exit_code == 0, result.output
    assert read_any(tmp_path / "hdl.npz").sensor["name"] == "velodyne:HDL-32E"


def _one(text: str, key: str, value: str) -> str:
    """``text`` with ``key: value`` in laser 0's line (in place of its own ``key`` when it has one)."""
    first, rest = text.split("\n- ", 1)[1].split("\n", 1)
    fields = dict(field.split(": ") for field in first.strip("{}").split(", "))
    line = "{" + ", ".join(f"{k}: {v}" for k, v in {**fields, key: value}.items()) + "}"
    return f"lasers:\n- {line}\n{rest}"


@pytest.mark.parametrize(
    "damage, message",
    [
        # ruamel's message spread over several lines with a drawing of the spot; the CLI prints one line
        (lambda text: text[: len(text) // 2], r"t.yaml: not readable YAML \(line \d+, column \d+: expected ',' or '}'"),
        # only 'vert_correction must be finite angles ...', without the laser or the value
        (lambda text: text.replace("vert_correction: -0.261799", "vert_correction: .nan"), r"laser 0: .* is nan; it"),
        (lambda text: text.replace("vert_correction: 0.000000", "vert_correction: 15.0", 1), r"laser 7: .* is 15;"),
        # the other corrections were not checked: NaN ones blamed the capture ('v.pcap: ray [0, 11, 0] has origin
        # [nan, nan, 0.0] m; the file is damaged') or named no file ('a ray flagged as hit has a non-finite range'),
        # huge ones read, with ranges of 1e9 m or origins 1e9 m away
        (lambda t: _one(t, "rot_correction", ".nan"), r"t.yaml: laser 0: rot_correction is nan; it must be a"),
        (lambda t: _one(t, "rot_correction", "-7"), r"laser 0: rot_correction is -7; it must be .* within \+-pi "),
        (lambda t: _one(t, "dist_correction", ".nan"), r"laser 0: dist_correction is nan; it must be a finite le"),
        (lambda t: _one(t, "dist_correction", "1e9"), r"laser 0: dist_correction is 1e\+09; .* within \+-10 m"),
        (lambda t: _one(t, "vert_offset_correction", ".inf"), r"laser 0: vert_offset_correction is inf; it must"),
        (lambda t: _one(t, "horiz_offset_correction", "-1e11"), r"laser 0: horiz_offset_correction is -1e\+11;"),
    ],
)
def test_a_damaged_calibration_table_is_named_on_one_line(tmp_path, damage, message):
    text = "lasers:\n" + "".join(
        f"- {{laser_id: {i}, rot_correction: 0.0, vert_correction: {np.radians(2 * i - 15) if i != 7 else 0:.6f}}}\n"
        for i in range(16)
    )
    (tmp_path / "t.yaml").write_text(damage(text))
    with pytest.raises(LogFormatError, match=message) as caught:
        read_velodyne(_capture(tmp_path), tmp_path / "t.yaml")
    assert "\n" not in str(caught.value)


def test_a_capture_cut_short_reads_its_complete_records(tmp_path):
    """tcpdump killed mid-write leaves the last record cut short: the packets before it are read, with a warning
    naming the byte; a capture whose first record is cut is refused."""
    path = _capture(tmp_path, packets=10)
    whole = read_velodyne(path)
    data = path.read_bytes()
    record = (len(data) - 24) // 10  # every record has the same length
    for keep in (24 + 9 * record + 7, 24 + 9 * record + 100):  # inside the last record's header, inside its data
        (tmp_path / "cut.pcap").write_bytes(data[:keep])
        with pytest.warns(TruncatedLogWarning, match=rf"cut.pcap: byte {24 + 9 * record}: the capture ends inside"):
            cut = read_velodyne(tmp_path / "cut.pcap")
        assert cut.ranges.size == whole.ranges.size * 9 // 10  # the nine whole packets
        np.testing.assert_array_equal(cut.ranges, whole.ranges[:, :, : cut.ranges.shape[2]])
    with warnings.catch_warnings():
        warnings.simplefilter("error", TruncatedLogWarning)
        (tmp_path / "first.pcap").write_bytes(data[: 24 + 50])
        with pytest.raises(LogFormatError, match="first.pcap: byte 24: the first record of .* is cut short"):
            read_velodyne(tmp_path / "first.pcap")
