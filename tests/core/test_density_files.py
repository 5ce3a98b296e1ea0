"""Density files: a saved density reads back; a damaged or inconsistent one is refused naming the file and table.

Byte-level damage (truncation, flips) is covered by the reader fuzzing in tests/io; these cases are files
that are valid archives with wrong contents, which fuzzing of a compressed file almost never produces.
"""

import json
import math

import numpy as np
import pytest

from mi_lidar.core.densities import NPRegDensity, PRegDensity
from mi_lidar.core.densities.tables import StateGrid, load_density, read_density, save_density
from mi_lidar.core.errors import LogFormatError, ParameterError
from tests.core.test_strict_json import strict_load

GRID = StateGrid(range_edges=[0.0, 5.0, 1.0e9], incidence_edges=[0.0, 45.0, 90.0], n_labels=2)


def saved(tmp_path, density) -> tuple:
    path = density.save(tmp_path / "good.npz")
    meta, tables = read_density(path)
    return meta, tables


def rewrite(tmp_path, meta, tables, grid="same", **changes):
    """A density file like ``meta``/``tables`` with ``changes`` to its tables (None removes one)."""
    tables = {k: v for k, v in {**tables, **changes}.items() if v is not None}
    grid = (None if meta["grid"] is None else StateGrid(**meta["grid"])) if grid == "same" else grid
    return save_density(tmp_path / "bad.npz", meta["name"], meta["params"], grid, tables)


def test_saved_densities_read_back(tmp_path):
    np_reg = NPRegDensity(grid=GRID)
    loaded = load_density(np_reg.save(tmp_path / "np.npz"))
    assert (
        loaded.grid == GRID and np.array_equal(loaded.mass, np_reg.mass) and np.array_equal(loaded.edges, np_reg.edges)
    )
    p_reg = load_density(PRegDensity(sigma=np.full((3, 2), 0.05)).save(tmp_path / "p.npz"))
    assert np.array_equal(p_reg.sigma, np.full((3, 2), 0.05))


def test_non_finite_notes_read_back_and_the_header_is_strict_json(tmp_path):
    """fit-sensor's notes list NP-Reg's candidate supports (reach inf: up to z_max) and NLLs that may be NaN; the
    header held ``Infinity`` and ``NaN``, which are not JSON. Now null, listed so that they read back as written."""
    notes = {"candidates": [[1.0, 5.0, 0.0, math.inf, 3.2]], "nll_misses": math.nan, "from": None}
    path = NPRegDensity(grid=GRID).save(tmp_path / "np.npz", notes=notes)
    with np.load(path) as data:
        header = strict_load(bytes(data["meta"]).decode())
    assert header["notes"] == {"candidates": [[1.0, 5.0, 0.0, None, 3.2]], "nll_misses": None, "from": None}
    meta, _ = read_density(path)
    assert json.dumps(meta["notes"]) == json.dumps(notes)  # Python's json writes NaN: NaN compares too
    assert load_density(path).grid == GRID


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(
        LogFormatError, match=r"nowhere\.npz: no such density file; write one with `mi-lidar fit-sensor`"
    ):
        load_density(tmp_path / "nowhere.npz")


@pytest.mark.parametrize("table", ["edges", "mass", "p_null"])
def test_non_finite_tables_are_refused(tmp_path, table):
    meta, tables = saved(tmp_path, NPRegDensity(grid=GRID))
    damaged = tables[table].astype(np.float64).copy()
    damaged.flat[0] = np.nan
    with pytest.raises(LogFormatError, match=rf"bad\.npz: damaged density file: tables \['{table}'\]"):
        load_density(rewrite(tmp_path, meta, tables, **{table: damaged}))


@pytest.mark.parametrize(
    "density, table, value, message",
    [
        (NPRegDensity(grid=GRID), "p_null", 1.5, r"np_reg: table p_null holds 1\.5"),
        (NPRegDensity(grid=GRID), "mass", -0.5, r"np_reg: table mass holds -0\.5"),
        (PRegDensity(), "sigma", 0.0, r"p_reg: table sigma holds 0\.0"),
        (PRegDensity(), "p_null", -0.1, r"p_reg: table p_null holds -0\.1"),
    ],
)
def test_values_outside_their_range_are_refused(tmp_path, density, table, value, message):
    meta, tables = saved(tmp_path, density)
    damaged = tables[table].astype(np.float64).copy()
    damaged.flat[-1] = value
    with pytest.raises(ParameterError, match=r"bad\.npz: " + message):
        load_density(rewrite(tmp_path, meta, tables, **{table: damaged}))


def test_inconsistent_tables_are_refused(tmp_path):
    meta, tables = saved(tmp_path, NPRegDensity(grid=GRID))
    with pytest.raises(ParameterError, match=r"np_reg: edges .* strictly increasing"):
        load_density(rewrite(tmp_path, meta, tables, edges=tables["edges"][::-1].copy()))
    meta, tables = saved(tmp_path, PRegDensity())
    with pytest.raises(ParameterError, match=r"p_reg: table mu has shape \(2, 3, 2\); expected \(3, 2\) \(1 label"):
        load_density(rewrite(tmp_path, meta, tables, mu=np.zeros((2, 3, 2))))
    with pytest.raises((LogFormatError, ParameterError), match=r"bad\.npz: .*'extra'"):
        load_density(rewrite(tmp_path, meta, tables, extra=np.zeros(3)))


@pytest.mark.parametrize(
    "grid, message",
    [
        ({"range_edges": [0.0, 5.0, 1.0e9], "n_beams": 0}, r"n_beams=0 must be an integer >= 1"),
        ({"range_edges": [5.0, 0.0]}, r"range_edges \[5\.0, 0\.0\] must be at least 2 strictly increasing"),
        ({"range_edges": [0.0, float("nan")]}, r"table range_edges holds nan"),
    ],
)
def test_a_bad_state_grid_is_refused(grid, message):
    with pytest.raises(ParameterError, match=message):
        StateGrid(**grid)


def test_a_bad_state_grid_in_a_file_names_the_file(tmp_path):
    meta, tables = saved(tmp_path, NPRegDensity(grid=GRID))
    meta["grid"]["n_labels"] = -1
    path = save_density(tmp_path / "bad.npz", meta["name"], meta["params"], None, tables)
    # StateGrid refuses the bad grid, so write it into the header of a grid-less file by hand
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    header = json.loads(bytes(arrays["meta"]).decode())
    header["grid"] = meta["grid"]
    arrays["meta"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    np.savez_compressed(path, **arrays)
    with pytest.raises(LogFormatError, match=r"bad\.npz: damaged density file: state grid: n_labels=-1"):
        load_density(path)
