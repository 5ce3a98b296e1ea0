"""Atomic file writes: write to a temporary file in the target folder, then rename.

A crash or an exception leaves the previous file (or nothing) and no temporary file behind, and
the final file gets the usual permissions (0666 minus the umask), not mkstemp's 0600. A run's output
folder (:func:`output_folder`) is made before the run and removed again, while still empty, when the
run fails. A scene XML and its assets folder (:func:`staged_scene`) are written together or not at all, and so
are the files of a report (:func:`staged_files`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _default_mode() -> int:
    """Permissions of a freshly created file: 0666 minus the process umask."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _naming(exc: OSError, path: str | os.PathLike) -> OSError:
    """``exc`` (same type, errno and reason) naming ``path``: the file the caller asked for, not a temporary one."""
    return type(exc)(exc.errno, exc.strerror, os.fspath(path))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    The temporary name keeps the destination's suffix, so libraries that choose a format by
    extension (OpenEXR, plyfile, laspy) work. The parent folder is created when missing.

    Raises:
        OSError: a failed write in the block (a full disk, ``ulimit -f``) is raised naming ``path``, not the
            temporary file or no file at all (``[Errno 27] File too large``; numpy's short write has no errno
            and becomes ``EIO``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    except OSError as exc:  # name the file the caller asked for, not the temporary one
        raise _naming(exc, path) from exc
    os.close(fd)
    tmp = Path(name)
    try:
        try:
            yield tmp
        except OSError as exc:  # a write that failed (disk full, size limit): name the file asked for
            if exc.filename not in (None, name):
                raise
            raise OSError(exc.errno or errno.EIO, exc.strerror or str(exc), os.fspath(path)) from exc
        os.chmod(tmp, _default_mode())
        try:
            os.replace(tmp, path)
        except OSError as exc:  # a folder of that name: name it, not the temporary file
            raise _naming(exc, path) from exc
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write(path: str | os.PathLike, write) -> Path:
    """Call ``write(stream)`` on a binary temporary file next to ``path``, then rename it to ``path``."""
    with atomic_path(path) as tmp, open(tmp, "wb") as stream:
        write(stream)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` as UTF-8, atomically.

    Returns:
        ``path`` as a Path.

    Raises:
        TypeError: ``text`` is not a str.
        UnicodeEncodeError: ``text`` holds a lone surrogate; the previous file stays.
    """
    if not isinstance(text, str):
        raise TypeError(f"{os.fspath(path)}: text must be a str, not {type(text).__name__}")
    return atomic_write(path, lambda stream: stream.write(text.encode("utf-8")))


@contextlib.contextmanager
def output_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Make the folder ``path`` (parents included) for a run's outputs; undo it if the run fails.

    Made first, a path that cannot be a folder fails before the run. When the block raises, the
    folders this call made are removed while they hold no file (empty subfolders such as ``cache/``
    go with them), so a run stopped by bad input leaves nothing behind; folders that existed before,
    and anything already written, are kept.
    """
    path = Path(path)
    made = [folder for folder in (path, *path.parents) if not folder.exists()]  # innermost first
    path.mkdir(parents=True, exist_ok=True)
    try:
        yield path
    except BaseException:
        for folder in made:
            for root, _, _ in os.walk(folder, topdown=False):
                with contextlib.suppress(OSError):  # not empty: something was written there
                    os.rmdir(root)
        raise


@contextlib.contextmanager
def _named_outside(stage: Path, folder: Path) -> Iterator[None]:
    """Re-raise an OSError of the block about a file in the temporary folder ``stage`` naming that file as it would be
    named in ``folder``, where it was to be moved (the temporary folder is gone when the message is read)."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None or not Path(exc.filename).is_relative_to(stage):
            raise
        raise _naming(exc, folder / Path(exc.filename).relative_to(stage)) from exc


@contextlib.contextmanager
def staged_files(folder: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder inside ``folder`` to write a set of files in (a report); when the block succeeds, every
    file written there is moved into ``folder`` (renames only, so each appears whole), replacing files of the same
    name and keeping the others; when it fails (a full disk, ``ulimit -f``, any exception), the temporary folder is
    removed and ``folder`` keeps what it held.

    Raises:
        OSError: a failed write in the block, naming the file as it would have been named in ``folder``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        stage = Path(tempfile.mkdtemp(prefix=".staged-", suffix=".tmp", dir=folder))
    except OSError as exc:  # name the folder asked for, not the temporary one
        raise _naming(exc, folder) from exc
    try:
        with _named_outside(stage, folder):
            yield stage
        for path in sorted(stage.iterdir()):
            os.replace(path, folder / path.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


@contextlib.contextmanager
def staged_scene(path: str | os.PathLike) -> Iterator[Path]:
    """Yield where to write the scene XML ``path`` and its ``<stem>_assets/``: both appear together or not at all.

    The block writes the XML at the yielded path and its assets in ``<stem>_assets/`` beside it, inside a
    temporary folder next to ``path`` (the XML must name its assets relative to itself). When the block
    succeeds, the assets folder and then the XML replace the previous ones (renames only, no copy); when it
    fails (a full disk, ``ulimit -f``, any exception), the temporary folder is removed and a previous scene
    and its assets stay as they were. Without this, a failed write left new assets beside no XML or beside
    the previous XML.

    Raises:
        OSError: a failed write in the block, naming the file it was writing as it would have been named in
            the output folder (not in the temporary one).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        stage = Path(tempfile.mkdtemp(prefix=f".{path.stem}.", suffix=".tmp", dir=path.parent))
    except OSError as exc:  # name the file the caller asked for, not the temporary folder
        raise _naming(exc, path) from exc
    assets = path.with_name(f"{path.stem}_assets")
    try:
        with _named_outside(stage, path.parent):
            yield stage / path.name
        _move_in(stage, path, assets)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _move_in(stage: Path, path: Path, assets: Path) -> None:
    """Move the staged XML and assets onto ``path`` and ``assets``, the previous assets aside first (and back
    if a rename fails)."""
    previous = stage / ".previous_assets"
    if assets.exists():
        os.replace(assets, previous)
    try:
        if (stage / assets.name).exists():
            os.replace(stage / assets.name, assets)
        os.replace(stage / path.name, path)
    except OSError as exc:
        if previous.exists():
            if assets.exists():
                os.replace(assets, stage / assets.name)
            os.replace(previous, assets)
        raise _naming(exc, path) from exc
