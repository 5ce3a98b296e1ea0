"""Report values as text (mi_lidar.io.markdown.plain): short numbers, readable keys, nesting kept visible."""

import numpy as np

from mi_lidar.io.markdown import effects_text, plain, spread, words


def test_floats_lists_and_nested_mappings_read_as_text():
    value = {"beta_prior": [0.0009999999310821295, 100.00000762939453], "correlation": {"shared": 0.999, "rho": 0.95}}
    assert plain(value) == "beta prior: [0.001, 100]; correlation: (shared: 0.999; rho: 0.95)"
    assert plain(5) == "5" and plain(True) == "True" and plain(None) == "None" and plain("np") == "np"


def test_many_numbers_read_as_their_spread_and_numpy_values_as_numbers():
    """The calibration and diagnosis reports wrote a per-beam bias as 180 floats, numpy arrays as
    ``[0.0359 0.0359 ...]`` and float32 scalars with every digit (``0.035947021``)."""
    bias = np.linspace(0.01, 0.05, 180).astype(np.float32)
    assert plain(bias) == "[180 values: min 0.01, median 0.03, max 0.05, RMS 0.03217]"
    assert plain({"bias": bias}) == "bias: [180 values: min 0.01, median 0.03, max 0.05, RMS 0.03217]"
    assert plain(np.float32(0.035947021)) == "0.03595" and plain(np.arange(3)) == "[0, 1, 2]"
    assert plain([1.0] * 8) == "[1, 1, 1, 1, 1, 1, 1, 1]"  # a few numbers stay listed
    assert spread([-0.02, 0.02]) == "2 values: min -0.02, median 0, max 0.02, RMS 0.02"
    assert words("mean_abs_change") == "mean abs change"


def test_effects_read_with_their_values_summarised():
    """compare's report began 'Model: range sigma 0.03 m, effects: range_bias(bias=[0.035947 0.035947 ...' with 180
    values; describe() keeps every value for scene XML."""
    from mi_lidar.core.effects import parse_effects

    effects = parse_effects("range_bias(bias=[" + ", ".join(["0.02"] * 16) + "]), incidence_dropout(gamma=2)")
    assert effects_text(effects) == (
        "range_bias (bias: [16 values: min 0.02, median 0.02, max 0.02, RMS 0.02]), "
        "incidence_dropout (law: cos; mode: stop; gamma: 2)"
    )
    assert effects_text([]) == "none" and len(effects[0].describe().split()) == 16


def test_a_p_value_that_underflowed_reads_as_a_bound():
    """diagnose printed 'held-out p = 0' and a ranking column of 0 where the p-value underflowed."""
    from mi_lidar.io.markdown import p_phrase, p_value

    assert p_value(0.0) == "< 1e-300" and p_phrase(0.0) == "p < 1e-300"
    assert p_value(2.34e-50) == "2.3e-50" and p_phrase(2.34e-50) == "p = 2.3e-50" and p_phrase(0.2, 1) == "p = 0.2"
