"""Text files that may be gzip-compressed (CARMEN logs): decoded lines, with the end of a stream cut short read
up to where it stops."""

from __future__ import annotations

import warnings
import zlib
from pathlib import Path

from mi_lidar.core.errors import LogFormatError, TruncatedLogWarning, unreadable


def text_lines(path: Path) -> list[str]:
    """Decoded text lines of a plain or gzip-compressed file (UTF-8; a byte order mark, which Windows editors write
    first, is dropped so that it does not hide the first line's first word).

    A gzip stream that ends early (a logger stopped mid-write) gives the text decompressed up to its end, with a
    :class:`~mi_lidar.core.errors.TruncatedLogWarning`; its last line is then usually cut short too.

    Raises:
        LogFormatError: Unreadable file, or a gzip stream that is corrupt or yields no text before it ends.
    """
    try:
        raw = path.read_bytes()
    except PermissionError as exc:
        raise unreadable(path, "log") from exc
    if raw[:2] == b"\x1f\x8b":
        raw = _gunzip(path, raw)
    return raw.decode("utf-8-sig", errors="replace").splitlines()


def _gunzip(path: Path, raw: bytes) -> bytes:
    """The text of the gzip members in ``raw``, up to where the stream ends (warned when that is mid-member)."""
    parts, rest = [], raw
    try:
        while rest:
            member = zlib.decompressobj(16 + zlib.MAX_WBITS)  # one gzip member, header and trailer checked
            parts.append(member.decompress(rest))
            if not member.eof:
                parts.append(member.flush())
                break
            rest = member.unused_data
    except zlib.error as exc:
        raise LogFormatError(f"{path}: corrupt gzip stream ({exc}); recompress the log or read the plain text") from exc
    text = b"".join(parts)
    if not member.eof:
        if not text:
            raise LogFormatError(f"{path}: truncated gzip stream: it ends before any text; copy the log again")
        warnings.warn(
            f"{path}: the gzip stream ends early, after {len(text):,} bytes of text (a logger stopped mid-write, or "
            "a partial copy?): reading the complete lines before its end",
            TruncatedLogWarning,
            stacklevel=4,
        )
    return text
