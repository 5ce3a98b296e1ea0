"""Catalog names (an effect or density is found whether written with dashes or underscores); parameter snapshots."""

import pytest

from mi_lidar.core.densities import NPRegDensity, parse_density
from mi_lidar.core.densities.tables import StateGrid
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.errors import ParameterError


def test_both_spellings_name_the_same_catalog_entry(tmp_path):
    """``fit-sensor --model np-reg`` writes dashes, the catalogs underscores: either is accepted."""
    from mi_lidar.core.params import catalog_name

    assert catalog_name(" np-reg ") == catalog_name("np_reg") == "np_reg"
    assert [e.name for e in parse_effects("range-bias(bias=0.02), incidence-dropout(law=cos)")] == [
        "range_bias",
        "incidence_dropout",
    ]
    path = NPRegDensity(grid=StateGrid(range_edges=[0.0, 5.0, 1.0e9], incidence_edges=[0.0, 90.0])).save(
        tmp_path / "np.npz"
    )
    assert isinstance(parse_density(f"np-reg(file={path})"), NPRegDensity)
    assert parse_density("physics(k=1e-4)").name == "physics"


def test_a_model_is_found_in_any_case_and_either_spelling():
    """benchmark-planar writes NP-Reg, fit-sensor np-reg: each verb takes the other's spelling (it refused it)."""
    from mi_lidar.core.params import choose_names

    known = ("M0", "M3b", "NP-Reg", "mi-lidar")
    assert choose_names(["np-reg", "M3B", "mi_lidar", " m0 "], known, "x") == ("NP-Reg", "M3b", "mi-lidar", "M0")
    with pytest.raises(
        ParameterError, match=r"^bench: unknown models \['M9'\]; choose from M0, M3b, NP-Reg, mi-lidar$"
    ):
        choose_names(["m0", "M9"], known, "bench: unknown models")
    with pytest.raises(ParameterError, match=r"unknown models \[\]; choose from"):
        choose_names([], known, "bench: unknown models")


def test_an_unknown_name_still_lists_the_catalog():
    with pytest.raises(ParameterError, match=r"unknown effect 'no-such'; the catalog has: .*range_bias"):
        parse_effects("no-such")


def test_a_snapshot_puts_back_the_values_it_copied():
    """Snapshot: what diagnose's refit_or_keep and the development path's realism guard restore. The copy is taken
    when the snapshot is: a change made later, even in place in the same Dr.Jit array, does not reach it."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    from mi_lidar.core.params import Snapshot

    bias, noise = parse_effects("range_bias(bias=0.02), range_noise(law=constant, sigma0=0.1)")
    bias.widen(3, 1)
    saved = Snapshot([bias, noise])
    dr.scatter(bias.params["bias"], mi.Float(0.5), mi.UInt32(1))  # in place: a copy of the dict would share it
    noise.params["sigma0"] = mi.Float(np.nan)  # replaced, as a failed fit step leaves it
    assert np.asarray(bias["bias"])[1] == 0.5
    saved.restore()
    assert np.array_equal(np.asarray(bias["bias"]), np.full(3, 0.02, np.float32))
    assert np.asarray(noise["sigma0"]).tolist() == [np.float32(0.1)]
    assert np.asarray(noise["sigma0"]).dtype == np.float32
