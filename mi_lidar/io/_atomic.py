"""Atomic file replacement shared by every writer of :mod:`mi_lidar.io`.

A writer asks :func:`atomic_path` for a temporary name in the destination folder, writes there,
and the file is renamed onto the destination only when the write succeeded; a crash or an
exception leaves the previous file (or nothing) and no temporary file behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _default_mode() -> int:
    """Permissions of a freshly created file: 0666 minus the process umask."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    Args:
        path: Final destination. Its parent folder is created when missing.

    Yields:
        A fresh temporary path in the same folder (same file system, so the rename is atomic).
        It keeps the destination's suffix so that libraries choosing a format by extension work.
        The final file gets the usual permissions (0666 minus the umask), not mkstemp's 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.chmod(tmp, _default_mode())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
