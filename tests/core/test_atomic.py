"""atomic_write_text: UTF-8 text written through a temporary file; a failed write leaves the old file and no litter."""

import errno
import os

import pytest

from mi_lidar.core import atomic
from mi_lidar.core.atomic import atomic_write_text


@pytest.fixture
def temporaries(monkeypatch):
    """The temporary files atomic_path creates, in order."""
    made = []
    mkstemp = atomic.tempfile.mkstemp

    def spy(*args, **kwargs):
        fd, name = mkstemp(*args, **kwargs)
        made.append(name)
        return fd, name

    monkeypatch.setattr(atomic.tempfile, "mkstemp", spy)
    return made


def test_text_round_trips_as_utf8_and_replaces_the_old_file(tmp_path, temporaries):
    path = tmp_path / "note.txt"
    path.write_bytes(b"old")
    assert atomic_write_text(path, "range \u00b5 m\n") == path
    assert path.read_bytes() == "range \u00b5 m\n".encode("utf-8")
    assert path.read_text(encoding="utf-8") == "range \u00b5 m\n"
    assert len(temporaries) == 1 and os.path.dirname(temporaries[0]) == str(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["note.txt"]


def test_text_that_cannot_be_encoded_leaves_the_old_file_and_no_temporary(tmp_path, temporaries):
    """A lone surrogate fails to encode inside the atomic block, after the temporary file exists."""
    path = tmp_path / "note.txt"
    path.write_text("old", encoding="utf-8")
    with pytest.raises(UnicodeEncodeError):
        atomic_write_text(path, "half \ud800 written")
    assert len(temporaries) == 1 and not os.path.exists(temporaries[0])
    assert path.read_text(encoding="utf-8") == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["note.txt"]


def test_a_failed_rename_leaves_the_old_file_and_no_temporary(tmp_path, temporaries, monkeypatch):
    path = tmp_path / "note.json"
    path.write_text("{}", encoding="utf-8")

    def refuse(src, dst):
        raise PermissionError(13, "Permission denied", os.fspath(dst))

    monkeypatch.setattr(atomic.os, "replace", refuse)
    with pytest.raises(PermissionError):
        atomic_write_text(path, '{"new": 1}')
    assert len(temporaries) == 1 and not os.path.exists(temporaries[0])
    assert path.read_text(encoding="utf-8") == "{}"
    assert [p.name for p in tmp_path.iterdir()] == ["note.json"]


def test_bytes_are_refused_and_the_old_file_stays(tmp_path):
    path = tmp_path / "note.txt"
    path.write_text("old", encoding="utf-8")
    with pytest.raises(TypeError, match="note.txt.*str"):
        atomic_write_text(path, b"new")
    assert path.read_text(encoding="utf-8") == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["note.txt"]


def test_a_folder_in_the_way_is_named_not_the_temporary_file(tmp_path):
    """The rename onto a folder failed naming the temporary file ('.scan.x1y2.tmp.npz: is a directory')."""
    (tmp_path / "scan.npz").mkdir()
    with pytest.raises(IsADirectoryError) as error:
        atomic_write_text(tmp_path / "scan.npz", "new")
    assert error.value.filename == str(tmp_path / "scan.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.npz"]


def test_an_output_folder_made_for_a_failed_run_is_removed_while_it_holds_no_file(tmp_path):
    target = tmp_path / "new" / "report"
    with pytest.raises(ValueError), atomic.output_folder(target / "cache") as folder:
        assert folder.is_dir()
        (target / "figures").mkdir()  # an empty subfolder the run made goes too
        raise ValueError("bad log")
    assert list(tmp_path.iterdir()) == []


def test_an_output_folder_keeps_what_existed_and_what_was_written(tmp_path):
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(ValueError), atomic.output_folder(existing / "report"):
        raise ValueError("bad log")
    assert list(existing.iterdir()) == []  # the folder that was there stays; the one made goes
    with pytest.raises(ValueError), atomic.output_folder(tmp_path / "partial") as folder:
        (folder / "cache").mkdir()
        (folder / "cache" / "frame.npz").write_bytes(b"done")
        raise ValueError("later stage")
    assert (tmp_path / "partial" / "cache" / "frame.npz").read_bytes() == b"done"
    with atomic.output_folder(tmp_path / "fine") as folder:
        (folder / "report.json").write_text("{}")
    assert folder.is_dir() and (folder / "report.json").is_file()


@pytest.mark.parametrize(
    "failure, code",
    [
        (OSError(errno.EFBIG, "File too large"), errno.EFBIG),  # a write past `ulimit -f`: no file named
        (OSError("22408 requested and 12800 written"), errno.EIO),  # numpy's short write: no errno either
    ],
)
def test_a_failed_write_names_the_file_asked_for(tmp_path, temporaries, failure, code):
    """The CLI printed '[Errno 27] File too large' or '22408 requested and 12800 written': no file, no fix."""
    path = tmp_path / "scan.bin"
    path.write_bytes(b"old")
    with pytest.raises(OSError) as caught, atomic.atomic_path(path):
        raise failure
    assert (caught.value.errno, caught.value.filename) == (code, str(path))
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["scan.bin"]


def tree(folder) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def write_staged_scene(xml, assets: dict[str, bytes], fail_at: str | None = None) -> None:
    (xml.parent / f"{xml.stem}_assets").mkdir()
    for name, content in assets.items():
        if name == fail_at:
            raise OSError(errno.EFBIG, "File too large", os.fspath(xml.parent / f"{xml.stem}_assets" / name))
        (xml.parent / f"{xml.stem}_assets" / name).write_bytes(content)
    xml.write_bytes(b"<scene new/>")


def test_a_staged_scene_replaces_the_previous_one_with_its_assets_or_leaves_it_whole(tmp_path):
    """calibrate and fit-scene wrote scene_assets/ before scene.xml: a write that failed midway left new assets
    beside the previous scene.xml (or beside none); stale assets of the previous scene stayed beside a new one."""
    out = tmp_path / "out"
    (out / "scene_assets").mkdir(parents=True)
    (out / "scene.xml").write_bytes(b"<scene old/>")
    (out / "scene_assets" / "stale.ply").write_bytes(b"old")
    previous = tree(out)
    with pytest.raises(OSError) as error, atomic.staged_scene(out / "scene.xml") as staged:
        write_staged_scene(staged, {"a.ply": b"new a", "b.ply": b"new b"}, fail_at="b.ply")
    assert error.value.filename == os.fspath(out / "scene_assets" / "b.ply")  # as named in the output folder
    assert tree(out) == previous and sorted(p.name for p in out.iterdir()) == ["scene.xml", "scene_assets"]
    with atomic.staged_scene(out / "scene.xml") as staged:
        write_staged_scene(staged, {"a.ply": b"new a"})
    assert tree(out) == {"scene.xml": b"<scene new/>", "scene_assets/a.ply": b"new a"}
    assert sorted(p.name for p in out.iterdir()) == ["scene.xml", "scene_assets"]


def test_staged_files_move_in_together_or_leave_the_folder_as_it_was(tmp_path):
    """benchmark-planar under `ulimit -f` said 'error: .../report/.benchmark-ndc82j3f/nll_by_range.png: file too
    large': a file of a staging folder that was removed before the message was read."""
    out = tmp_path / "report"
    out.mkdir()
    (out / "a.json").write_bytes(b"old a")
    (out / "notes.txt").write_bytes(b"kept")
    with pytest.raises(OSError) as error, atomic.staged_files(out) as staging:
        (staging / "a.json").write_bytes(b"new a")
        raise OSError(errno.EFBIG, "File too large", os.fspath(staging / "b.png"))
    assert error.value.filename == os.fspath(out / "b.png")  # as named in the report folder
    assert tree(out) == {"a.json": b"old a", "notes.txt": b"kept"} and len(list(out.iterdir())) == 2
    with atomic.staged_files(out) as staging:
        (staging / "a.json").write_bytes(b"new a")
        (staging / "b.png").write_bytes(b"new b")
    assert tree(out) == {"a.json": b"new a", "b.png": b"new b", "notes.txt": b"kept"} and len(list(out.iterdir())) == 3
