import hashlib
import json

import numpy as np
import pytest

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.patterns import ouster
from mi_lidar.io import range_digest, read_any, read_ouster
from mi_lidar.io.ouster import destagger, restagger

from .conftest import data_file, ouster_sdk_file
from .synth import ouster_metadata, ouster_payloads, pcap_bytes, write_ouster

OUSTER = "ouster/OS-1-32-G_v2.1.1_1024x10.pcap"


@pytest.fixture(scope="module")
def real():
    return read_ouster(data_file(OUSTER))


def test_real_frame_matches_vendor_range_digest(real):
    digest = json.loads(data_file("ouster/OS-1-32-G_v2.1.1_1024x10_digest.json").read_text())
    assert real.shape == (1, 32, 1024)
    assert range_digest(real) == digest["scans"][0]["RANGE"]
    # The packet-level digest is over each packet's (32 pixels x 16 columns) uint32 block in turn.
    staggered = restagger(real.attributes["range_mm"][0], real.sensor["pixel_shift_by_row"])
    packets = staggered.reshape(32, 64, 16).transpose(1, 0, 2)
    assert hashlib.md5(np.ascontiguousarray(packets).tobytes()).hexdigest() == digest["packet_hash"]["RANGE"]
    assert real.sensor["frame_ids"] == [int(digest["scans"][0]["FRAME_ID"])]


SDK_CAPTURES = {  # capture -> profile; the SDK's digests are over the staggered fields in these dtypes
    "OS-2-32-U0_v2.0.0_1024x10": "LEGACY",
    "OS-2-128-U1_v2.3.0_1024x10": "RNG19_RFL8_SIG16_NIR16",
    "OS-0-32-U1_v2.2.0_1024x10": "RNG19_RFL8_SIG16_NIR16_DUAL",
    "OS-0-128-U1_v2.3.0_1024x10": "RNG15_RFL8_NIR8",
}
SDK_FIELDS = {  # digest key -> (attribute, dtype of the SDK's field)
    "RANGE": ("range_mm", np.uint32),
    "RANGE2": ("range2_mm", np.uint32),
    "SIGNAL": ("signal", np.uint16),
    "SIGNAL2": ("signal2", np.uint16),
    "REFLECTIVITY": ("reflectivity", np.uint8),
    "REFLECTIVITY2": ("reflectivity2", np.uint8),
    "NEAR_IR": ("near_ir", np.uint16),
}


@pytest.mark.parametrize("capture", list(SDK_CAPTURES))
def test_every_profile_matches_the_sdk_digests(capture):
    pcap = ouster_sdk_file(f"{capture}.pcap")
    digest = json.loads(ouster_sdk_file(f"{capture}_digest.json").read_text())
    log = read_ouster(pcap, metadata=ouster_sdk_file(f"{capture}.json"))
    assert log.sensor["profile"] == SDK_CAPTURES[capture]
    assert log.sensor["frame_ids"] == [int(scan["FRAME_ID"]) for scan in digest["scans"]]
    shift = log.sensor["pixel_shift_by_row"]
    for index, scan in enumerate(digest["scans"]):
        checked = []
        for key, (name, dtype) in SDK_FIELDS.items():
            if key in scan:
                field = np.ascontiguousarray(restagger(log.attributes[name][index], shift), dtype=dtype)
                assert hashlib.md5(field.tobytes()).hexdigest() == scan[key], f"{capture} scan {index} {key}"
                checked.append(key)
        assert {"RANGE", "REFLECTIVITY", "NEAR_IR"} <= set(checked)
    if SDK_CAPTURES[capture] == "RNG15_RFL8_NIR8":  # 8 mm units: ranges reach beyond 65.535 m
        assert np.nanmax(log.ranges) > 65.535
        assert np.all(log.attributes["range_mm"] % 8 == 0)


def test_real_frame_misses_ranges_and_geometry(real):
    assert real.attributes["valid"].all()
    assert abs((1 - real.hit.mean()) - 0.1666) < 1e-3
    assert np.all(np.isnan(real.ranges[~real.hit]))
    np.testing.assert_array_equal(
        real.ranges[real.hit], (real.attributes["range_mm"][real.hit] / 1000.0).astype(np.float32)
    )
    assert 2.0 < np.nanmin(real.ranges) and np.nanmax(real.ranges) < 250.0
    np.testing.assert_allclose(np.linalg.norm(real.directions, axis=-1), 1.0, atol=1e-6)
    elevation = np.degrees(np.arcsin(real.directions[0, :, :, 2]))
    np.testing.assert_allclose(elevation[:, 0], real.sensor["beam_altitude_deg"], atol=1e-4)
    # Destaggering aligns the columns: every row of a column looks in the same azimuth.
    azimuth = np.degrees(np.arctan2(real.directions[0, ..., 1], real.directions[0, ..., 0]))
    spread = (azimuth - azimuth[:1] + 180) % 360 - 180
    assert np.abs(spread).max() < 0.1 < 360 / 1024
    # Beam origins sit 15.8 mm from the axis, 36.18 mm above the sensor base.
    radius = np.linalg.norm(real.origins[0, ..., :2] + 0.015806 * real.directions[0, ..., :2], axis=-1)
    np.testing.assert_allclose(radius, 0.015806, atol=1e-6)
    np.testing.assert_allclose(real.origins[0, ..., 2] + 0.015806 * real.directions[0, ..., 2], 0.03618, atol=1e-6)
    span = real.times.max() - real.times.min()
    assert 0.09 < span < 0.1


def test_destagger_inverts():
    image = np.arange(4 * 10).reshape(4, 10)
    shift = [0, 3, 6, 9]
    np.testing.assert_array_equal(restagger(destagger(image, shift), shift), image)
    np.testing.assert_array_equal(destagger(image, shift)[1], np.roll(image[1], 3))


@pytest.mark.parametrize("profile, nested", [("LEGACY", False), ("RNG19_RFL8_SIG16_NIR16", True)])
def test_synthetic_profiles_decode_exactly(tmp_path, profile, nested):
    rng = np.random.default_rng(5)
    staggered = rng.integers(300, 80_000, (8, 64)).astype(np.uint32)
    staggered[rng.random(staggered.shape) < 0.2] = 0
    log = read_ouster(write_ouster(tmp_path, staggered, profile=profile, nested=nested))
    assert log.shape == (1, 8, 64)
    np.testing.assert_array_equal(restagger(log.attributes["range_mm"][0], log.sensor["pixel_shift_by_row"]), staggered)
    assert log.sensor["profile"] == profile
    np.testing.assert_array_equal(log.hit[0], destagger(staggered > 0, log.sensor["pixel_shift_by_row"]))
    rows = np.arange(8)[:, None]
    np.testing.assert_array_equal(log.attributes["signal"][0], np.broadcast_to(100 + rows, (8, 64)))
    np.testing.assert_array_equal(log.attributes["reflectivity"][0], np.broadcast_to(rows, (8, 64)))


def test_dual_and_low_bandwidth_profiles(tmp_path):
    staggered = (np.random.default_rng(6).integers(40, 8000, (8, 32)) * 8).astype(np.uint32)
    dual = read_ouster(write_ouster(tmp_path, staggered, profile="RNG19_RFL8_SIG16_NIR16_DUAL"))
    shift = dual.sensor["pixel_shift_by_row"]
    np.testing.assert_array_equal(restagger(dual.attributes["range_mm"][0], shift), staggered)
    np.testing.assert_array_equal(restagger(dual.attributes["range2_mm"][0], shift), staggered + 1000)
    np.testing.assert_array_equal(dual.attributes["reflectivity2"][0][:, 0], np.arange(8))
    np.testing.assert_array_equal(dual.attributes["signal2"][0][:, 0], 50 + np.arange(8))
    staggered[0, :4] = [65_536, 100_000, 200_000, 0x7FFF * 8]  # beyond 16 bits of mm
    low = read_ouster(write_ouster(tmp_path, staggered, profile="RNG15_RFL8_NIR8"))
    np.testing.assert_array_equal(restagger(low.attributes["range_mm"][0], shift), staggered)
    assert np.nanmax(low.ranges) == np.float32(0x7FFF * 8 / 1000.0)
    np.testing.assert_array_equal(low.attributes["near_ir"][0][:, 0], ((200 + np.arange(8)) >> 4) << 4)


def test_partial_frames_are_kept_as_invalid_columns(tmp_path):
    staggered = np.full((4, 64), 5000, np.uint32)
    payloads = ouster_payloads(staggered, frame_id=1, columns=np.arange(32, 64))
    payloads += ouster_payloads(staggered, frame_id=2, t0_ns=10**18 + 10**8)
    (tmp_path / "p.json").write_text(json.dumps(ouster_metadata(4, 64)))
    (tmp_path / "p.pcap").write_bytes(pcap_bytes(payloads, 7502))
    log = read_ouster(tmp_path / "p.pcap")
    assert log.shape == (2, 4, 64)
    assert log.sensor["frame_ids"] == [1, 2]
    valid = restagger(log.attributes["valid"], log.sensor["pixel_shift_by_row"])
    assert not valid[0][:, :32].any() and valid[0][:, 32:].all() and valid[1].all()
    assert log.hit.sum() == 4 * 32 + 4 * 64
    assert np.all(np.diff(restagger(log.times, log.sensor["pixel_shift_by_row"])[0, 0]) > 0)


def test_fragmented_ip_packets_are_reassembled(tmp_path):
    staggered = np.full((4, 32), 1234, np.uint32)
    (tmp_path / "f.json").write_text(json.dumps(ouster_metadata(4, 32)))
    (tmp_path / "f.pcap").write_bytes(pcap_bytes(ouster_payloads(staggered), 7502, fragment=480))
    log = read_ouster(tmp_path / "f.pcap")
    assert log.hit.all() and np.all(log.ranges == np.float32(1.234))


def test_wrong_profile_or_metadata_is_reported(tmp_path):
    path = write_ouster(tmp_path, np.full((8, 32), 1000, np.uint32))
    meta = ouster_metadata(8, 32, "RNG19_RFL8_SIG16_NIR16")
    (tmp_path / "rng19.json").write_text(json.dumps(meta))
    with pytest.raises(LogFormatError, match=r"no 1792-byte lidar packets \(profile RNG19_RFL8_SIG16_NIR16"):
        read_ouster(path, metadata=tmp_path / "rng19.json")
    (tmp_path / "narrow.json").write_text(json.dumps(ouster_metadata(8, 16)))
    with pytest.raises(LogFormatError, match="measurement id 16 >= 16 columns"):
        read_ouster(path, metadata=tmp_path / "narrow.json")
    (tmp_path / "bad.json").write_text('{"beam_altitude_angles": [1, 2]}')
    with pytest.raises(LogFormatError, match="missing field 'beam_azimuth_angles'"):
        read_ouster(path, metadata=tmp_path / "bad.json")
    meta["data_format"]["udp_profile_lidar"] = "FUSA_RNG15"
    (tmp_path / "fusa.json").write_text(json.dumps(meta))
    with pytest.raises(LogFormatError, match="udp_profile_lidar 'FUSA_RNG15'"):
        read_ouster(path, metadata=tmp_path / "fusa.json")
    del meta["data_format"]["pixel_shift_by_row"]
    (tmp_path / "unshifted.json").write_text(json.dumps(meta))
    with pytest.raises(LogFormatError, match="missing field 'pixel_shift_by_row'"):
        read_ouster(path, metadata=tmp_path / "unshifted.json")


@pytest.mark.parametrize("nested", [False, True])
def test_decoder_and_pattern_read_one_geometry(tmp_path, nested):
    # One metadata parser and one beam geometry: the decoded log's rays are the firing pattern's (the times
    # come from the packets' own stamps).
    path = write_ouster(tmp_path, np.full((8, 64), 3000, np.uint32), nested=nested)
    log = read_ouster(path)
    pattern = ouster(path.with_suffix(".json"))
    assert pattern.name == "os-1-synth"
    np.testing.assert_allclose(log.directions[0], pattern.directions(), atol=1e-7)
    np.testing.assert_allclose(log.origins[0], pattern.origins(), atol=1e-7)


def test_dispatch_picks_ouster_from_sidecar_json(tmp_path):
    path = write_ouster(tmp_path, np.full((4, 16), 2000, np.uint32))
    assert read_any(path).sensor["name"] == "ouster:OS-1-SYNTH"
