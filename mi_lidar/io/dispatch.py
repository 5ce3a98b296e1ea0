"""Read and write any supported scan format, chosen by file extension.

=====================================  ===================  =========================================
extension                              read                 write
=====================================  ===================  =========================================
``.npz``                               mi-lidar log         mi-lidar log (all scans)
``.log``, ``.log.gz``, ``.clf``        CARMEN ``FLASER``    -
                                       or ``ROBOTLASER1``
``.pcap``                              Ouster (when a       -
                                       metadata ``.json``
                                       sits next to it or
                                       ``metadata=`` is
                                       given) or Velodyne
``.bin``, ``.pcd.bin``                 KITTI / nuScenes     KITTI (hits, x y z intensity)
``.ply``                               PLY                  PLY (hits, standard fields)
``.pcd``                               PCD                  PCD (organized H x W, NaN misses)
``.las``, ``.laz``                     LAS                  LAS 1.4 (hits, extra dims)
``.bag``; ROS 2 bag folder             ROS 1/2 bag          ROS 2 bag folder (``fmt="rosbag2"``, all
(``metadata.yaml``), ``.db3``,                              scans, organized PointCloud2 with a
``.mcap``                                                   field per attribute, poses on ``/tf``)
``.exr``                               EXR range image      EXR range image (float32 channels)
``.png``                               -                    range-image preview
=====================================  ===================  =========================================

Single-scan formats write scan ``scan`` (default 0); a log of several scans must name the scan.
"""

from __future__ import annotations

import os
from pathlib import Path

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.io import carmen, exr, kitti, las, ouster, pcd, ply, rosbag, velodyne
from mi_lidar.io._pcap import read_udp
from mi_lidar.io.preview import range_image_png
from mi_lidar.io.signature import KINDS, check_signature

READ_FORMATS = ("npz", "carmen", "ouster", "velodyne", "bin", "ply", "pcd", "las", "rosbag", "exr")
WRITE_FORMATS = ("npz", "bin", "ply", "pcd", "las", "rosbag2", "exr", "png")
MULTI_SCAN_FORMATS = ("npz", "rosbag2")  # the written formats that hold every scan of a log; the others hold one
_SUFFIX_FORMATS = {
    ".npz": "npz",
    ".log": "carmen",
    ".clf": "carmen",
    ".gz": "carmen",
    ".bin": "bin",
    ".ply": "ply",
    ".pcd": "pcd",
    ".las": "las",
    ".laz": "las",
    ".bag": "rosbag",
    ".db3": "rosbag",
    ".mcap": "rosbag",
    ".exr": "exr",
    ".png": "png",
}

EXTENSIONS = {  # the extensions of each read format, for messages beside signature.KINDS' nouns
    "npz": ".npz",
    "carmen": ".log, .log.gz, .clf",
    "pcap": ".pcap",
    "bin": ".bin",
    "ply": ".ply",
    "pcd": ".pcd",
    "las": ".las, .laz",
    "exr": ".exr",
    "png": ".png",
}


def detect_format(path: str | os.PathLike, for_writing: bool = False) -> str:
    """The format name of ``path`` from its extension (and, for ``.pcap``, its packets).

    Raises:
        LogFormatError: Unknown extension, or a ``.gz`` that is not a CARMEN ``.log.gz``.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".gz" and not path.name.lower().endswith((".log.gz", ".clf.gz")):
        raise LogFormatError(f"{path}: unknown compressed format; expected a CARMEN .log.gz")
    if for_writing and suffix in ("", ".bag"):
        return "rosbag2"
    if not for_writing and path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "rosbag"
        storage = sorted(p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
        if storage:
            raise LogFormatError(
                f"{path}: a ROS 2 bag folder without metadata.yaml (it holds {', '.join(storage)}); rebuild the "
                f"metadata with `ros2 bag reindex {path}`"
            )
        named = "pcap" if suffix == ".pcap" else _SUFFIX_FORMATS.get(suffix, "rosbag")
        if named != "rosbag":  # drive.exr/, scan.ply/: a file's name on a folder (an unpacked archive, a typo)
            raise LogFormatError(
                f"{path}: a folder, but its name ends in {suffix!r}, which names {KINDS[named]}: give the file "
                "itself, or the folder's file that is one"
            )
        known = ", ".join(sorted(set(_SUFFIX_FORMATS) | {".pcap"}))
        raise LogFormatError(
            f"{path}: a folder without metadata.yaml, so not a ROS 2 bag; give a ROS 2 bag folder or a file: {known}"
        )
    if suffix == ".pcap":
        return "pcap"  # read only: write_any names the formats it writes
    if suffix not in _SUFFIX_FORMATS:
        if for_writing:  # was the extensions read, .pcap and .log among them, to a writer that refuses them
            known = ", ".join(s for s, fmt in _SUFFIX_FORMATS.items() if fmt in WRITE_FORMATS and s != ".laz")
            raise LogFormatError(
                f"{path}: unknown extension {suffix!r}; writable: {known} or a ROS 2 bag (.bag or no extension)"
            )
        known = ", ".join(sorted(set(_SUFFIX_FORMATS) | {".pcap"}))
        raise LogFormatError(f"{path}: unknown extension {suffix!r}; supported: {known} or a ROS 2 bag folder")
    return _SUFFIX_FORMATS[suffix]


def _read_pcap(path: Path, metadata=None, calibration=None, model=None, **options) -> Log:
    """Ouster when metadata is given or sits next to the capture, else Velodyne.

    A Velodyne capture without ``calibration`` uses the calibration YAML next to it when the
    folder holds exactly one.
    """
    sidecar = path.with_suffix(".json")
    if metadata is not None or (sidecar.is_file() and calibration is None and model is None):
        if calibration is not None or model is not None:
            raise LogFormatError(
                f"{path}: calibration= (--calibration) and model= (--model) are for Velodyne captures; "
                "an Ouster capture takes metadata= (--metadata) only"
            )
        return ouster.read_ouster(path, metadata=metadata or sidecar)
    sizes = {len(p) for p in read_udp(path).payloads}
    if velodyne.PACKET_SIZE in sizes:
        if calibration is None:
            tables = sorted(path.parent.glob("*.yaml"))
            calibration = tables[0] if len(tables) == 1 else None  # the one calibration table beside it
        return velodyne.read_velodyne(path, calibration=calibration, model=model, **options)
    raise LogFormatError(
        f"{path}: no Velodyne data packets and no Ouster metadata JSON next to it; pass metadata= "
        "(Ouster) or calibration= (Velodyne)"
    )


def _format_name(fmt: str) -> str:
    """What a read format is, with its extensions: ``a CARMEN log (.log, .log.gz, .clf)``."""
    return f"{KINDS[fmt]} ({EXTENSIONS[fmt]})" if fmt in EXTENSIONS else KINDS[fmt]


def read_any(path: str | os.PathLike, formats: tuple[str, ...] | None = None, **options) -> Log:
    """Read any supported file into a :class:`Log` (see the module table).

    Args:
        path: The file (or ROS 2 bag folder).
        formats: The formats (names :func:`detect_format` gives) the caller takes, e.g. ``("carmen",)``;
            a file of another format is refused, saying what it is; a file whose extension no format claims
            is read as the caller's only format. None: any.
        **options: Passed to the format's reader, e.g. ``metadata=`` (Ouster), ``calibration=``,
            ``model=``, ``return_mode=`` (Velodyne), ``min_range=`` (point clouds), ``topic=``
            (bags), ``columns=`` (``.bin``), ``message=`` (CARMEN).

    Raises:
        LogFormatError: Unknown format or one not in ``formats``, a file whose first bytes say it is not of the
            format its extension names (empty, another format's, damaged:
            :func:`mi_lidar.io.signature.check_signature`), any defect the format's reader reports, or values no
            measurement has (:meth:`Log.check_values`).
        PoseError: a pose that is not a finite rigid transform.
    """
    path = Path(path)
    try:
        fmt = detect_format(path)
    except LogFormatError:
        if formats is None or len(formats) != 1 or path.is_dir():
            raise
        fmt = formats[0]  # a name no format claims (e.g. intel.txt, aces.gz): read it as the one the caller takes
    if formats is not None and fmt not in formats:
        wanted = " or ".join(_format_name(name) for name in formats)
        raise LogFormatError(
            f"{path}: {_format_name(fmt)} by its extension; expected {wanted}: give the file in that format (for a "
            "log converted from one, the original)"
        )
    if fmt == "png":
        raise LogFormatError(f"{path}: PNG previews cannot be read back; read the scan's source file")
    readers = {
        "npz": Log.load,
        "carmen": carmen.read_carmen,
        "bin": kitti.read_bin_log,
        "ply": ply.read_ply_log,
        "pcd": pcd.read_pcd_log,
        "las": las.read_las_log,
        "rosbag": rosbag.read_rosbag_log,
        "exr": exr.read_exr_log,
    }
    if path.is_file():
        check_signature(path, fmt)
    log = _read_pcap(path, **options) if fmt == "pcap" else readers[fmt](path, **options)
    if fmt != "npz":  # Log.load checks its values
        log.check_values(path)
    log.source = str(path)
    return log


def log_output_format(path: str | os.PathLike, n_scans: int) -> str:
    """The format a log of ``n_scans`` scans is written in at ``path`` (from its extension), checked before
    the log is made: every scan is kept (a one-scan format only for a one-scan log), and a range image
    (``.png``) is a preview, not a log.

    Raises:
        LogFormatError: no extension, one no writer takes, or a one-scan format for several scans; the
            message names the extensions that fit.
    """
    path = Path(path)
    try:
        fmt = detect_format(path, for_writing=True) if path.suffix else None
    except LogFormatError:
        fmt = None
    if fmt in MULTI_SCAN_FORMATS or (n_scans == 1 and fmt in WRITE_FORMATS and fmt != "png"):
        return fmt
    one_scan = ".ply, .pcd, .bin, .las, .exr"  # the one-scan log writers of write_any (.png is a preview)
    fits = f".npz or .bag (a ROS 2 bag folder){'' if n_scans > 1 else f'; one scan also {one_scan}'}"
    raise LogFormatError(f"{path}: cannot write {n_scans} scan(s) as {path.suffix or 'no extension'!r}; use {fits}")


def write_any(log: Log, path: str | os.PathLike, fmt: str | None = None, scan: int | None = None) -> Path:
    """Write ``log`` in the format ``fmt`` (or the one ``path``'s extension names).

    Args:
        log: The log.
        path: Destination file (a folder for ``rosbag2``).
        fmt: One of :data:`WRITE_FORMATS`; from the extension when None.
        scan: Scan to write for single-scan formats; required when the log holds several scans.

    Raises:
        LogFormatError: Unknown or read-only format, or a multi-scan log without ``scan``.
    """
    path = Path(path)
    fmt = fmt or detect_format(path, for_writing=True)
    if fmt not in WRITE_FORMATS:
        raise LogFormatError(f"{path}: cannot write format {fmt!r}; writable formats: {', '.join(WRITE_FORMATS)}")
    if fmt == "npz":
        return log.save(path)
    if fmt == "rosbag2":
        return rosbag.write_rosbag_log(log, path)
    if scan is None:
        if log.n_scans != 1:
            raise LogFormatError(
                f"{path}: the log holds {log.n_scans} scans and {fmt} holds one; pass scan=<index> "
                "(--scan) or write a .npz log or a ROS 2 bag"
            )
        scan = 0
    if not -log.n_scans <= scan < log.n_scans:
        n = log.n_scans
        raise LogFormatError(
            f"{path}: cannot write scan {scan}: the log holds {n} scan{'s' if n != 1 else ''}; give a scan index "
            f"from 0 to {n - 1} (or from -{n} to -1, counted from the end)"
        )
    if fmt == "png":
        one = log.scan(scan)
        title = f"{one.sensor.get('name', 'scan')} scan {scan}"
        valid = one.attributes.get("valid")
        return range_image_png(
            path, one.ranges[0], title=title, hit=one.hit[0], valid=None if valid is None else valid[0]
        )
    writers = {
        "bin": kitti.write_bin_log,
        "ply": ply.write_ply_log,
        "pcd": pcd.write_pcd_log,
        "las": las.write_las_log,
        "exr": exr.write_exr_log,
    }
    return writers[fmt](log, path, scan=scan)
