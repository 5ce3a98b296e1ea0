"""An effect prints as it is written in XML and on the command line."""

from mi_lidar.core.effects import parse_effects


def test_a_model_s_effects_print_as_written():
    """docs/writing_an_effect.md builds ``model.effects``; printing it showed '<...RangeNoise object at 0x...>'."""
    effects = parse_effects("range_bias(bias=0.02), range_noise(law=physics, k=1e-5)")
    assert repr(effects[0]) == "range_bias(bias=0.02)"
    assert str(effects) == f"[range_bias(bias=0.02), {effects[1].describe()}]"
    assert str(effects[1]).startswith("range_noise(law=physics, ") and "k=1e-05" in str(effects[1])
