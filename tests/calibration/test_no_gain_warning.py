"""calibrate warns when its fitted values score the held-out rays worse than the values it started from."""

from mi_lidar.calibration.result import no_gain_warnings


def test_a_fit_that_gains_on_the_held_out_rays_is_not_warned_about():
    assert no_gain_warnings(initial_nll=1.5, counting_nll=1.45, fitted_nll=1.40) == []
    assert no_gain_warnings(initial_nll=1.5, counting_nll=1.5, fitted_nll=1.5) == []


def test_a_fit_that_loses_says_so_with_both_figures():
    """The README's off-road p_hit calibration on a log of its own scene: 1.40612 -> 1.40670, counting 1.40980."""
    (warning,) = no_gain_warnings(initial_nll=1.40612, counting_nll=1.40980, fitted_nll=1.40670)
    assert "1.40670 against 1.40612 nats/ray" in warning
    assert "counting estimate, which scored 1.40980 (try --no-counting-start)" in warning
    (warning,) = no_gain_warnings(initial_nll=1.40612, counting_nll=1.40612, fitted_nll=1.40670)
    assert "counting" not in warning
