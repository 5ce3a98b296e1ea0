"""Synthetic Ouster captures for the I/O benchmark: a LEGACY-profile pcap plus its metadata JSON.

The packet layout is the sensor's (``../shared/data/README.md``): each UDP payload holds
``columns_per_packet`` columns of [timestamp u64, measurement id u16, frame id u16, encoder count
u32, ``beams`` pixels of (range u32 in mm, 20 bits used; reflectivity u16; signal u16; NIR u16;
unused u16), status u32]. Packets go to port 7502 in unfragmented Ethernet/IPv4/UDP frames on
the loopback address, as in the real OS-1-32 capture.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

LIDAR_PORT = 7502
ENCODER_TICKS = 90112  # encoder counts per revolution (LEGACY firmware)
COLUMNS_PER_PACKET = 16
PIXEL = np.dtype([("range", "<u4"), ("reflectivity", "<u2"), ("signal", "<u2"), ("near_ir", "<u2"), ("unused", "<u2")])


def _column_dtype(beams: int) -> np.dtype:
    """One measurement block (column) of a LEGACY packet with ``beams`` pixels."""
    return np.dtype(
        [
            ("timestamp", "<u8"),
            ("measurement_id", "<u2"),
            ("frame_id", "<u2"),
            ("encoder", "<u4"),
            ("pixels", PIXEL, (beams,)),
            ("status", "<u4"),
        ]
    )


def _frame(payload: bytes) -> bytes:
    """An Ethernet/IPv4/UDP frame from 127.0.0.1 to 127.0.0.1:``LIDAR_PORT`` carrying ``payload``."""
    udp = struct.pack(">HHHH", LIDAR_PORT, LIDAR_PORT, 8 + len(payload), 0)
    ip = struct.pack(
        ">BBHHHBBH4s4s",
        0x45,
        0,
        20 + len(udp) + len(payload),
        1,
        0,
        128,
        17,
        0,
        bytes([127, 0, 0, 1]),
        bytes([127, 0, 0, 1]),
    )
    checksum = sum(struct.unpack(">10H", ip))
    checksum = (checksum & 0xFFFF) + (checksum >> 16)
    ip = ip[:10] + struct.pack(">H", ~((checksum & 0xFFFF) + (checksum >> 16)) & 0xFFFF) + ip[12:]
    return b"\0" * 12 + b"\x08\x00" + ip + udp + payload


def write_legacy_capture(
    folder: Path,
    beams: int = 128,
    columns: int = 1024,
    seed: int = 0,
) -> tuple[Path, Path, dict[str, np.ndarray]]:
    """Write one full frame of a synthetic LEGACY-profile Ouster sensor.

    Args:
        folder: Existing folder for ``os-synthetic.pcap`` and ``os-synthetic.json``.
        beams: Pixels per column.
        columns: Columns per frame (a multiple of 16).
        seed: Seed of the random pixel values.

    Returns:
        ``(pcap, metadata, written)``: the two paths and the **staggered** (beams, columns)
        arrays written, ``range_mm`` (about 17% zeros, i.e. no return), ``reflectivity``,
        ``signal`` and ``near_ir``, columns indexed by measurement id.
    """
    rng = np.random.default_rng(seed)
    written = {
        "range_mm": np.where(
            rng.random((beams, columns)) < 0.17, 0, rng.integers(300, 120_000, (beams, columns))
        ).astype(np.uint32),
        "reflectivity": rng.integers(0, 1 << 16, (beams, columns), dtype=np.uint16),
        "signal": rng.integers(0, 1 << 16, (beams, columns), dtype=np.uint16),
        "near_ir": rng.integers(0, 1 << 16, (beams, columns), dtype=np.uint16),
    }
    blocks = np.zeros(columns, dtype=_column_dtype(beams))
    measurement = np.arange(columns)
    blocks["timestamp"] = 1_700_000_000_000_000_000 + measurement * (100_000_000 // columns)
    blocks["measurement_id"] = measurement
    blocks["frame_id"] = 7
    blocks["encoder"] = measurement * ENCODER_TICKS // columns
    blocks["status"] = 0xFFFFFFFF
    pixels = blocks["pixels"]
    pixels["range"] = written["range_mm"].T | (rng.integers(0, 1 << 12, (columns, beams), dtype=np.uint32) << 20)
    for name in ("reflectivity", "signal", "near_ir"):
        pixels[name] = written[name].T

    altitude = np.linspace(22.5, -22.5, beams)
    metadata = {
        "beam_altitude_angles": altitude.tolist(),
        "beam_azimuth_angles": np.tile([4.2, 1.4, -1.4, -4.2], beams // 4).tolist(),
        "lidar_origin_to_beam_origin_mm": 15.806,
        "lidar_mode": f"{columns}x10",
        "prod_line": f"OS-1-{beams}",
        "lidar_to_sensor_transform": [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
        "imu_to_sensor_transform": [1, 0, 0, 6.253, 0, 1, 0, -11.775, 0, 0, 1, 7.645, 0, 0, 0, 1],
        "build_rev": "v2.1.1",
        "proto_rev": "v1.1.1",
        "status": "RUNNING",
        "data_format": {
            "columns_per_frame": columns,
            "columns_per_packet": COLUMNS_PER_PACKET,
            "column_window": [0, columns - 1],
            "pixels_per_column": beams,
            "pixel_shift_by_row": np.tile([18, 12, 6, 0], beams // 4).tolist(),
        },
    }
    records = []
    for first in range(0, columns, COLUMNS_PER_PACKET):
        frame = _frame(blocks[first : first + COLUMNS_PER_PACKET].tobytes())
        stamp = 1_700_000_000 * 1_000_000 + first * 100_000 // columns
        records.append(struct.pack("<IIII", stamp // 1_000_000, stamp % 1_000_000, len(frame), len(frame)) + frame)
    pcap, meta_path = folder / "os-synthetic.pcap", folder / "os-synthetic.json"
    pcap.write_bytes(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1) + b"".join(records))
    meta_path.write_text(json.dumps(metadata))
    return pcap, meta_path, written
