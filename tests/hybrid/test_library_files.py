"""PrimitiveLibrary.save writes each file atomically and the index last: no temporary files, and a save that
stops midway leaves the previous library loadable."""

import numpy as np
import pytest

from mi_lidar.hybrid.classes import CLASS_ID
from mi_lidar.hybrid.model import EllipsoidSet
from mi_lidar.hybrid.primitives import Primitive, PrimitiveLibrary


def library(*names: str) -> PrimitiveLibrary:
    label = CLASS_ID["rock"]
    means = np.array([[0.0, 0.0, 0.0], [0.4, 0.0, 0.1]])
    ellipsoids = EllipsoidSet(means, np.tile(np.eye(3) * 0.04, (2, 1, 1)), np.full(2, 0.9), label=label)
    return PrimitiveLibrary([Primitive(n, label, ellipsoids, means.min(0) - 0.5, means.max(0) + 0.5) for n in names])


def test_save_leaves_only_the_library_files(tmp_path):
    folder = tmp_path / "lib"
    library("a", "b").save(folder)
    library("a", "b", "c").save(folder)  # overwrites a and b in place
    assert sorted(p.name for p in folder.iterdir()) == ["a.npz", "b.npz", "c.npz", "library.json"]
    assert [r["id"] for r in PrimitiveLibrary.load(folder).rows()] == ["a", "b", "c"]


def test_a_save_that_fails_midway_keeps_the_previous_index_and_no_temporary(tmp_path, monkeypatch):
    folder = tmp_path / "lib"
    library("a", "b").save(folder)
    before = (folder / "library.json").read_text()
    savez, calls = np.savez_compressed, []

    def fail_on_second(file, **arrays):
        calls.append(file)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        savez(file, **arrays)

    monkeypatch.setattr(np, "savez_compressed", fail_on_second)
    with pytest.raises(OSError, match="No space"):
        library("x", "y").save(folder)
    assert len(calls) == 2
    assert (folder / "library.json").read_text() == before
    assert sorted(p.name for p in folder.iterdir()) == ["a.npz", "b.npz", "library.json", "x.npz"]
    assert [r["id"] for r in PrimitiveLibrary.load(folder).rows()] == ["a", "b"]


def test_an_index_of_another_version_or_a_missing_primitive_is_named(tmp_path):
    """A library.json of version 7 was read as version 1; a primitive it lists but the folder lacks was 'not a
    primitive file (FileNotFoundError: ...)'."""
    import json

    from mi_lidar.core.errors import SceneError

    folder = tmp_path / "lib"
    library("a", "b").save(folder)
    index = json.loads((folder / "library.json").read_text())
    (folder / "library.json").write_text(json.dumps({**index, "version": 7}))
    with pytest.raises(SceneError, match=r"library.json: format 'mi-lidar-primitives' version 7; this mi-lidar reads"):
        PrimitiveLibrary.load(folder)
    (folder / "library.json").write_text(json.dumps(index))
    (folder / "b.npz").unlink()
    with pytest.raises(SceneError, match=r"b\.npz: no such primitive file, yet library.json lists it; extract"):
        PrimitiveLibrary.load(folder)
