"""The evaluations' dataset cache belongs to its input, its settings and the code that wrote it."""

import json
import math

import numpy as np

from mi_lidar.apps import cache
from mi_lidar.apps.cache import cache_key, load_datasets, save_datasets, source_digest
from tests.core.test_strict_json import strict_load


def test_source_digest_changes_with_any_python_file(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    (tmp_path / "notes.txt").write_text("not code")
    first = source_digest(tmp_path)
    (tmp_path / "notes.txt").write_text("still not code")
    assert source_digest(tmp_path) == first
    (tmp_path / "sub" / "b.py").write_text("y = 3\n")
    assert source_digest(tmp_path) != first


def test_a_cache_written_by_other_code_is_not_read(tmp_path, monkeypatch):
    log = tmp_path / "log.txt"
    log.write_text("FLASER ...")
    file = tmp_path / "datasets.npz"
    key = cache_key(log, {"runs": 2})
    save_datasets(file, key, {"poses": np.zeros((3, 3))}, {"real": np.ones((1, 3, 4))}, [{"model": "M0"}])
    states, ranges, rows = load_datasets(file, cache_key(log, {"runs": 2}))
    assert np.array_equal(ranges["real"], np.ones((1, 3, 4))) and rows == [{"model": "M0"}]
    assert load_datasets(file, cache_key(log, {"runs": 3})) is None
    monkeypatch.setattr(cache, "code_digest", lambda: "another version")
    assert load_datasets(file, cache_key(log, {"runs": 2})) is None


def test_non_finite_benchmark_figures_read_back_and_the_cache_holds_strict_json(tmp_path):
    """A benchmark row of a log without misses has a NaN NLL of the misses; the cache held ``NaN``, not JSON."""
    log = tmp_path / "log.txt"
    log.write_text("FLASER ...")
    file, key = tmp_path / "datasets.npz", cache_key(log, {"runs": 2})
    rows = [{"model": "M0", "test_nll_misses": math.nan, "miss_threshold": math.inf, "samples": {"f1": 0.9}}]
    save_datasets(file, key, {"poses": np.zeros((3, 3))}, {"real": np.ones((1, 3, 4))}, rows)
    with np.load(file) as z:
        assert strict_load(str(z["benchmark"]))["rows"][0]["test_nll_misses"] is None
    assert json.dumps(load_datasets(file, key)[2]) == json.dumps(rows)  # Python's json writes NaN: NaN compares too
