"""What a file holds, from its first bytes: the check :func:`mi_lidar.io.dispatch.read_any` makes before a reader runs.

Formats with a signature (PLY, LAS/LAZ, ``.npz`` and ``.npy``, EXR, pcap, SQLite/MCAP/ROS 1 bags, PNG, gzip,
PCD) are recognised by their leading bytes, so a file of one format under another's extension, an empty file
and random bytes where a signature belongs are refused before parsing, naming what the file is and the
extension to give it. Formats without one (KITTI ``.bin``, CARMEN text) are refused only when the bytes are
another format's signature; their readers check the rest.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mi_lidar.core.errors import LogFormatError, unreadable
from mi_lidar.io._pcap import PCAP_MAGIC


@dataclass(frozen=True)
class Signature:
    """The leading bytes of one kind of file.

    Attributes:
        fmt: The read format of :mod:`mi_lidar.io.dispatch` it belongs to (``"npy"``, ``"png"``, ``"gzip"``
            and ``"pcapng"`` are none).
        magic: The byte strings such a file starts with.
        kind: What the file is, for messages ("a PLY point cloud").
        fix: What to do with such a file given under another extension.
    """

    fmt: str
    magic: tuple[bytes, ...]
    kind: str
    fix: str


SIGNATURES = (
    Signature("ply", (b"ply\n", b"ply\r\n"), "a PLY point cloud", "rename it to .ply"),
    Signature("las", (b"LASF",), "a LAS/LAZ point cloud", "rename it to .las (.laz when compressed)"),
    Signature("npz", (b"PK\x03\x04", b"PK\x05\x06"), "a zip archive (an .npz log?)", "rename it to .npz"),
    Signature("npy", (b"\x93NUMPY",), "a numpy .npy array", "rename it to .npy (pose files and pattern tables)"),
    Signature("exr", (b"v/1\x01",), "an OpenEXR image", "rename it to .exr"),
    Signature("pcap", tuple(PCAP_MAGIC), "a pcap capture", "rename it to .pcap"),
    Signature(
        "pcapng",
        (b"\x0a\x0d\x0d\x0a",),
        "a pcapng capture",
        "mi-lidar reads classic pcap: convert it with `editcap -F pcap IN.pcapng OUT.pcap`",
    ),
    Signature(
        "gzip",
        (b"\x1f\x8b\x08",),
        "a gzip file",
        "mi-lidar reads gzip only as a CARMEN .log.gz: rename it so, or decompress it (gunzip)",
    ),
    Signature("rosbag", (b"SQLite format 3\x00",), "an SQLite database (a ROS 2 bag's .db3?)", "rename it to .db3"),
    Signature("rosbag", (b"\x89MCAP",), "an MCAP file (a ROS 2 bag's .mcap?)", "rename it to .mcap"),
    Signature("rosbag", (b"#ROSBAG V2.0",), "a ROS 1 bag", "rename it to .bag"),
    Signature(
        "png", (b"\x89PNG\r\n\x1a\n",), "a PNG image", "PNG previews cannot be read back; read the scan's source"
    ),
    Signature("pcd", (b"# .PCD", b"VERSION ", b"VERSION\t", b"FIELDS "), "a PCD point cloud", "rename it to .pcd"),
)
HEAD_BYTES = max(len(m) for s in SIGNATURES for m in s.magic)
KINDS = {  # what each read format of the dispatch table is, for messages
    "npz": "an mi-lidar .npz log",
    "carmen": "a CARMEN log",
    "bin": "a KITTI/nuScenes .bin point file",
    "ply": "a PLY point cloud",
    "pcd": "a PCD point cloud",
    "las": "a LAS/LAZ point cloud",
    "rosbag": "a ROS bag",
    "exr": "an EXR range image",
    "pcap": "a pcap capture",
    "npy": "a numpy .npy array",
    "png": "a PNG preview",
}
OPTIONAL = {"carmen": ("gzip",), "pcd": (), "bin": ()}  # formats without a signature: the others they may look like
SHORTEST_HEADLESS_MAGIC = 4  # a headerless float file matches a signature of 2 or 3 bytes by chance: ignore those


def read_head(path: Path, size: int = HEAD_BYTES) -> bytes:
    """The first ``size`` bytes of ``path``.

    Raises:
        LogFormatError: the file cannot be opened (permission denied, or another system error), named with the fix.
    """
    try:
        with open(path, "rb") as stream:
            return stream.read(size)
    except PermissionError as exc:
        raise unreadable(path) from exc
    except OSError as exc:
        raise LogFormatError(f"{path}: cannot read the file ({exc.strerror or exc}); check the path") from exc


def sniff(head: bytes, headerless: bool = False) -> tuple[Signature, bytes] | None:
    """The signature ``head`` starts with and the magic bytes it matched, or None.

    Args:
        head: The file's first bytes (:data:`HEAD_BYTES` suffice).
        headerless: The file should be raw numbers (a KITTI ``.bin``): only signatures of at least
            :data:`SHORTEST_HEADLESS_MAGIC` bytes count, shorter ones match a float by chance.
    """
    for signature in SIGNATURES:
        for magic in signature.magic:
            if head.startswith(magic) and (not headerless or len(magic) >= SHORTEST_HEADLESS_MAGIC):
                return signature, magic
    return None


def check_signature(path: Path, fmt: str) -> None:
    """Refuse ``path`` before the ``fmt`` reader runs when its first bytes say it is not such a file.

    Args:
        path: A file (not a folder).
        fmt: Its read format from the extension (a key of :data:`KINDS`).

    Raises:
        LogFormatError: an empty file; a file whose bytes are another format's signature (named, with the
            extension to give it); a file without the signature ``fmt`` requires (cut inside it, damaged or
            not such a file).
    """
    head = read_head(path)
    if not head:
        raise LogFormatError(f"{path}: empty file (0 bytes), not {KINDS[fmt]}; re-create or copy it again")
    found = sniff(head, headerless=fmt == "bin")
    if found is not None and found[0].fmt != fmt and found[0].fmt not in OPTIONAL.get(fmt, ()):
        signature, magic = found
        raise LogFormatError(f"{path}: {signature.kind} (it starts with {magic!r}), not {KINDS[fmt]}: {signature.fix}")
    if found is None and fmt not in OPTIONAL:
        magics = [m for s in SIGNATURES if s.fmt == fmt for m in s.magic]
        if any(m.startswith(head) for m in magics):
            raise LogFormatError(
                f"{path}: {len(head)} byte(s), cut off inside the signature of {KINDS[fmt]} (truncated); re-create "
                "or copy it again"
            )
        raise LogFormatError(
            f"{path}: not {KINDS[fmt]}: such a file starts with {magics[0]!r}, this one with {head[:8]!r} (damaged, "
            "or another format); re-create or copy it again"
        )
