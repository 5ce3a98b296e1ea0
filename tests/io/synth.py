"""Builders of small synthetic sensor files for the I/O tests (pcap captures, CARMEN logs)."""

from __future__ import annotations

import json
import struct

import numpy as np


def pcap_bytes(
    payloads: list[bytes], port: int, start: float = 1_600_000_000.0, step: float = 1e-3, fragment: int | None = None
) -> bytes:
    """A little-endian microsecond pcap of Ethernet/IPv4/UDP datagrams to ``port``.

    ``fragment`` splits each IPv4 packet into fragments of that many payload bytes (multiple of 8).
    """
    out = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    for index, payload in enumerate(payloads):
        udp = struct.pack(">HHHH", port, port, 8 + len(payload), 0) + payload
        pieces = [(0, udp)] if fragment is None else [(o, udp[o : o + fragment]) for o in range(0, len(udp), fragment)]
        for position, (offset, body) in enumerate(pieces):
            more = fragment is not None and position < len(pieces) - 1
            ip = (
                struct.pack(
                    ">BBHHHBBH4s4s",
                    0x45,
                    0,
                    20 + len(body),
                    index & 0xFFFF,
                    (0x2000 if more else 0) | (offset // 8),
                    64,
                    17,
                    0,
                    bytes(4),
                    bytes(4),
                )
                + body
            )
            frame = bytes(12) + b"\x08\x00" + ip
            t = start + index * step
            out.append(struct.pack("<IIII", int(t), int(round((t % 1) * 1e6)), len(frame), len(frame)) + frame)
    return b"".join(out)


def ouster_metadata(height: int, width: int, profile: str = "LEGACY", nested: bool = False) -> dict:
    """Metadata of a synthetic ``height`` x ``width`` Ouster sensor (legacy flat or nested JSON)."""
    altitude = np.linspace(15.0, -15.0, height).round(3).tolist()
    azimuth = [(-3.0, 1.0, 3.0, -1.0)[u % 4] for u in range(height)]
    shift = [(0, 6, 12, 18)[u % 4] for u in range(height)]
    fmt = {
        "columns_per_frame": width,
        "columns_per_packet": 16,
        "pixels_per_column": height,
        "pixel_shift_by_row": shift,
        "column_window": [0, width - 1],
        "udp_profile_lidar": profile,
    }
    transform = [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1]
    if nested:
        return {
            "beam_intrinsics": {
                "beam_altitude_angles": altitude,
                "beam_azimuth_angles": azimuth,
                "lidar_origin_to_beam_origin_mm": 15.806,
            },
            "lidar_intrinsics": {"lidar_to_sensor_transform": transform},
            "lidar_data_format": fmt,
            "config_params": {"lidar_mode": f"{width}x10", "udp_profile_lidar": profile},
            "sensor_info": {"prod_line": "OS-1-SYNTH"},
        }
    return {
        "beam_altitude_angles": altitude,
        "beam_azimuth_angles": azimuth,
        "data_format": fmt,
        "lidar_mode": f"{width}x10",
        "lidar_origin_to_beam_origin_mm": 15.806,
        "lidar_to_sensor_transform": transform,
        "prod_line": "OS-1-SYNTH",
    }


def ouster_payloads(
    range_mm: np.ndarray,
    profile: str = "LEGACY",
    frame_id: int = 7,
    t0_ns: int = 10**18,
    columns: np.ndarray | None = None,
) -> list[bytes]:
    """UDP payloads carrying a staggered (H, W) range image (mm), 16 columns per packet.

    ``columns`` restricts the measurement ids sent (a partial frame); all by default.
    """
    height, width = range_mm.shape
    columns = np.arange(width) if columns is None else np.asarray(columns)
    pixel = {"LEGACY": 12, "RNG19_RFL8_SIG16_NIR16": 12, "RNG19_RFL8_SIG16_NIR16_DUAL": 16, "RNG15_RFL8_NIR8": 4}[
        profile
    ]
    payloads = []
    for start in range(0, len(columns), 16):
        ids = columns[start : start + 16]
        body = [] if profile == "LEGACY" else [struct.pack("<HH", 1, frame_id) + bytes(28)]
        for m in ids:
            stamp = t0_ns + int(m) * 97_656
            if profile == "LEGACY":
                header = struct.pack("<QHHI", stamp, int(m), frame_id, int(m) * 88)
            else:
                header = struct.pack("<QHH", stamp, int(m), 1)
            pixels = b"".join(_pixel(profile, int(range_mm[u, m]), u) for u in range(height))
            assert len(pixels) == height * pixel
            body.append(header + pixels + (struct.pack("<I", 0xFFFFFFFF) if profile == "LEGACY" else b""))
        if profile != "LEGACY":
            body.append(bytes(32))
        payloads.append(b"".join(body))
    return payloads


def _pixel(profile: str, range_mm: int, row: int) -> bytes:
    """One pixel block: range, reflectivity = row, signal = 100 + row, near-IR = 200 + row."""
    if profile == "LEGACY":
        return struct.pack("<IHHHH", range_mm, row, 100 + row, 200 + row, 0)
    if profile == "RNG19_RFL8_SIG16_NIR16":
        return struct.pack("<IBBHHH", range_mm, row, 0, 100 + row, 200 + row, 0)
    if profile == "RNG19_RFL8_SIG16_NIR16_DUAL":  # second return 1 m further, reflectivity in byte 3
        return struct.pack(
            "<IIHHHH", range_mm | row << 24, (range_mm + 1000) | row << 24, 100 + row, 50 + row, 200 + row, 0
        )
    return struct.pack("<HBB", range_mm >> 3, row, (200 + row) >> 4)


def write_ouster(folder, range_mm: np.ndarray, profile: str = "LEGACY", nested: bool = False, **options):
    """Write ``synth.pcap`` + ``synth.json`` into ``folder`` and return the pcap path."""
    height, width = range_mm.shape
    (folder / "synth.json").write_text(json.dumps(ouster_metadata(height, width, profile, nested)))
    path = folder / "synth.pcap"
    path.write_bytes(pcap_bytes(ouster_payloads(range_mm, profile, **options), 7502))
    return path


def velodyne_payloads(
    distances: np.ndarray,
    azimuth_cdeg: np.ndarray,
    mode: int = 0x37,
    product: int = 0x22,
    stamp_us: int = 1_000_000,
    packet_us: float = 1327.104,
) -> list[bytes]:
    """Velodyne payloads from (P, 12, 32) raw distances and (P, 12) block azimuths (0.01 deg)."""
    payloads = []
    for p in range(len(distances)):
        blocks = b"".join(
            struct.pack("<HH", 0xEEFF, int(azimuth_cdeg[p, b]) % 36000)
            + b"".join(struct.pack("<HB", int(distances[p, b, c]), (b + c) % 256) for c in range(32))
            for b in range(12)
        )
        payloads.append(blocks + struct.pack("<IBB", int(stamp_us + p * packet_us) % 3_600_000_000, mode, product))
    return payloads


def carmen_text(scans: int = 3, beams: int = 180, max_range: float = 81.83, times=None) -> str:
    """A CARMEN log with ``scans`` FLASER lines (range ``1 + i/100`` m, beam 5 a miss), timed ``times`` (s; default
    ``10 + s``); scan ``s`` is on line ``4 + 2 s``."""
    lines = ["# synthetic", "PARAM robot_frontlaser_offset 0.0 nohost 0"]
    for s in range(scans):
        readings = [1 + i / 100 for i in range(beams)]
        readings[5] = max_range
        pose = (s * 1.0, 2.0, 0.5 * s)
        stamp = 10.0 + s if times is None else times[s]
        lines.append("ODOM 0 0 0 0 0 0 0.1 host 0.1")
        lines.append(
            "FLASER {} {} {} {} {} {} {} {} {} host {}".format(
                beams, " ".join(f"{r:.2f}" for r in readings), *pose, *pose, stamp, stamp
            )
        )
    return "\n".join(lines) + "\n"
