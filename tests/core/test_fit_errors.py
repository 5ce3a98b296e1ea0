"""The one fitter's errors say what is not finite, where, and what is likely wrong."""

import drjit as dr
import numpy as np
import pytest

from mi_lidar.core.errors import FitError, ParameterError
from mi_lidar.core.fitting import FitVariable, adam_fit


def root_sum(values, step):
    """``sum(sqrt(x))``: finite at x = 0, where its derivative is not."""
    loss = dr.sum(dr.sqrt(values()["beam_offsets.elevation#0"]))
    dr.backward(loss)
    return float(loss[0])


def test_a_finite_loss_with_a_non_finite_gradient_names_the_values_and_the_cause():
    x = FitVariable("beam_offsets.elevation#0", np.array([1.0, 0.0, 4.0]), lower=0.0)
    with pytest.raises(FitError) as caught:
        adam_fit([x], root_sum, 5)
    message = str(caught.value)
    assert "the loss is finite (3)" in message
    assert "beam_offsets.elevation#0 at 1 (1 of 3 values)" in message
    assert "not differentiable" in message and "singular point" in message
    assert "metres" not in message  # the loss is finite: the log's units are not what is wrong
    assert isinstance(caught.value, ParameterError)  # callers that catch parameter errors still do


def test_a_non_finite_loss_points_at_the_log_and_the_scene():
    def log_of_zero(values, step):
        loss = -dr.sum(dr.log(values()["p"] - 0.5))  # log(0) at the start
        dr.backward(loss)
        return float(loss[0])

    with pytest.raises(FitError, match=r"the loss is inf, not finite: .*in metres"):
        adam_fit([FitVariable("p", np.array([0.5]))], log_of_zero, 5)
