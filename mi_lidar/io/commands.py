"""The ``mi-lidar convert`` and ``mi-lidar info`` commands as plain functions (the CLI wires them).

Examples:
    >>> convert("scan.pcap", "scan.pcd", scan=0)          # Ouster/Velodyne frame -> organized PCD
    >>> info("intel-corrected.log.gz")["shape"]
    [910, 1, 180]
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mi_lidar.io.dispatch import detect_format, read_any, write_any


def convert(
    in_path: str | os.PathLike,
    out_path: str | os.PathLike,
    to: str | None = None,
    scan: int | None = None,
    **read_options,
) -> Path:
    """Read ``in_path`` (any readable format) and write it to ``out_path``.

    Args:
        in_path: Source file (format from its extension; see :mod:`mi_lidar.io.dispatch`).
        out_path: Destination; its extension picks the format unless ``to`` is given.
        to: Output format name (``npz bin ply pcd las rosbag2 exr png``).
        scan: Scan to write for single-scan output formats (required for multi-scan logs).
        **read_options: Passed to the reader (``metadata=``, ``calibration=``, ``min_range=``...).

    Returns:
        The written path.

    Raises:
        LogFormatError: Unreadable input, unknown format, or a multi-scan log without ``scan``.
    """
    log = read_any(in_path, **read_options)
    return write_any(log, out_path, fmt=to, scan=scan)


STREAMED_FORMATS = ("pcap", "rosbag")  # captures cut from a stream: the first scan may start mid-revolution


def scan_period(log, streamed: bool) -> float | None:
    """The median time between the starts of consecutive scans (s), counting whole scans only.

    Args:
        log: Any log.
        streamed: The log was cut from a stream (a capture): its first scan may start mid-revolution,
            so its start does not begin a period (the scans between two others are whole).

    Returns:
        The period, or None when no scan is known to be whole (one scan; a capture of two).
    """
    starts = log.times.reshape(log.n_scans, -1).min(axis=1)
    periods = np.diff(starts)[1 if streamed else 0 :]
    return float(np.median(periods)) if periods.size else None


def info(path: str | os.PathLike, **read_options) -> dict:
    """Summarize a scan file as a JSON-able dict.

    Keys: ``path``, ``format``, ``sensor`` (name, or the pattern of a simulated log), ``shape``
    ([S, H, W]), ``rays``, ``miss_fraction`` (of valid rays), ``invalid_fraction`` (grid cells no
    measurement filled), ``range_m`` (min, median, max over hits), ``time_span_s``,
    ``scan_period_s`` (median time between the starts of whole scans, see :func:`scan_period`),
    ``trajectory_length_m``, ``attributes``, ``simulated`` (``{"seed", "effects"}`` of a log
    ``mi_lidar.simulate`` wrote, else None), ``no_return_m`` (the no-return value of a log read from a CARMEN log,
    ``sensor["max_range_m"]``, m: ``inf`` when the log has none; None for other logs).
    """
    log = read_any(path, **read_options)
    fmt = detect_format(path)
    valid = log.attributes.get("valid", np.ones(log.shape, dtype=bool)).astype(bool)
    hits = log.ranges[log.hit]
    steps = np.linalg.norm(np.diff(log.poses[:, :3, 3], axis=0), axis=1)
    return {
        "path": str(path),
        "format": fmt,
        "sensor": log.sensor.get("name") or log.sensor.get("pattern") or "unknown",
        "shape": list(log.shape),
        "rays": log.n_rays,
        "miss_fraction": float(1.0 - log.hit[valid].mean()) if valid.any() else 1.0,
        "invalid_fraction": float(1.0 - valid.mean()),
        "range_m": [float(hits.min()), float(np.median(hits)), float(hits.max())] if hits.size else None,
        "time_span_s": float(log.times.max() - log.times.min()),
        "scan_period_s": scan_period(log, streamed=fmt in STREAMED_FORMATS),
        "trajectory_length_m": float(steps.sum()),
        "attributes": sorted(log.attributes),
        "no_return_m": float(log.sensor["max_range_m"]) if "max_range_m" in log.sensor else None,
        "simulated": {"seed": int(log.sensor["seed"]), "effects": list(log.sensor.get("effects", []))}
        if "seed" in log.sensor
        else None,
    }
