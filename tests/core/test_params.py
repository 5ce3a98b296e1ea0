"""Catalog names: an effect or density is found whether its name is written with dashes or underscores."""

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


def test_an_unknown_name_still_lists_the_catalog():
    with pytest.raises(ParameterError, match=r"unknown effect 'no-such'; the catalog has: .*range_bias"):
        parse_effects("no-such")
