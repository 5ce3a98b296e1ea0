"""Report values as text (mi_lidar.io.markdown.plain): short numbers, readable keys, nesting kept visible."""

from mi_lidar.io.markdown import plain


def test_floats_lists_and_nested_mappings_read_as_text():
    value = {"beta_prior": [0.0009999999310821295, 100.00000762939453], "correlation": {"shared": 0.999, "rho": 0.95}}
    assert plain(value) == "beta prior: [0.001, 100]; correlation: (shared: 0.999; rho: 0.95)"
    assert plain(5) == "5" and plain(True) == "True" and plain(None) == "None" and plain("np") == "np"
