"""A figure that rounds to zero prints without a minus sign, in the terminal tables and the HTML report."""

import numpy as np
import pytest

from mi_lidar.cli.tables import figure
from mi_lidar.core.decimals import fixed


@pytest.mark.parametrize(
    ("value", "digits", "text"),
    [
        (-0.00001, 4, "0.0000"),
        (-0.00001, 3, "0.000"),
        (-0.0, 3, "0.000"),
        (np.float64(-0.0004), 3, "0.000"),
        (-0.5, 3, "-0.500"),
        (-0.0005001, 3, "-0.001"),
        (1.23456, 2, "1.23"),
    ],
)
def test_fixed_drops_the_minus_of_a_rounded_zero(value, digits, text):
    assert fixed(value, digits) == text


def test_figure_prints_zero_plain_and_nan_as_a_dash():
    assert figure(-0.00001, 4) == "0.0000"
    assert figure(-0.5) == "-0.500"
    assert figure(float("nan")) == "-"
    assert figure(np.nan, 4) == "-"


def test_report_sample_cells_have_no_negative_zero():
    from mi_lidar.planar.report import _sample_cells

    samples = {
        "range_error_median": 0.01234,
        "range_error_p90": -0.0001,
        "f1": 0.9,
        "histogram_l1": 0.2,
        "histogram_l1_draws": 0.1,
        "histogram_l1_draws_se": -0.0002,
        "crps_mean": 0.05,
        "crps_mean_se": 0.001,
        "crps_median": -0.00001,
    }
    cells = _sample_cells(samples)
    assert cells == ("0.012", "0.000", "0.900", "0.200 / 0.100 ± 0.000", "0.050 ± 0.001 / 0.0000")
    assert not any("-0.0" in cell for cell in cells)


@pytest.mark.parametrize(
    ("value", "digits", "text"),
    [(-0.04, 1, "+0.0"), (0.0, 0, "+0"), (-75.0, 1, "-75.0"), (60.5, 1, "+60.5"), (-0.4, 0, "+0")],
)
def test_signed_figures_keep_a_plus_and_never_print_minus_zero(value, digits, text):
    """The beam groups of ``compare`` name their bearings signed ("-75.0..-60.5 deg", "+0.0..+14.5 deg")."""
    assert fixed(value, digits, signed=True) == text
