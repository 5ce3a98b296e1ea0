"""The one fitter stops a fit that has stopped gaining, and only then."""

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.fitting import FitVariable, adam_fit, stalled


def quadratic(target: float):
    """The objective ``(x - target)^2`` of one variable, as adam_fit calls it."""

    def objective(values, step):
        loss = dr.square(values()["x"] - target)
        dr.backward(loss)
        return float(loss[0])

    return objective


def test_stalled_looks_back_one_window():
    best = [1.0] * 5 + [0.5] * 20
    assert not stalled(best[:16], 1e-3, window=15, min_steps=10)  # the drop is within the window
    assert stalled(best, 1e-3, window=15, min_steps=10)
    assert not stalled(best, None, window=15, min_steps=10)
    assert not stalled(best[:8], 1e-3, window=5, min_steps=10)  # too few steps yet


def test_a_fit_at_its_optimum_stops_and_a_fit_on_its_way_does_not():
    at_optimum = adam_fit([FitVariable("x", np.array([2.0]), scale=0.1)], quadratic(2.0), 100, tolerance=1e-6)
    assert at_optimum.stopped_early and at_optimum.steps_run == 20  # min_steps: nothing to gain from the start
    far = adam_fit([FitVariable("x", np.array([0.0]), scale=0.1)], quadratic(2.0), 60, tolerance=1e-6)
    assert not far.stopped_early and far.steps_run == 60  # 0.03 per step: still gaining at the end
    # Adam's steps are about lr * scale = 0.03, decaying along the cosine: at most 0.03 * 33 = 1 in total
    assert 0.5 < far.values["x"][0] <= 1.0 + 1e-3


def test_a_logit_variable_starting_on_its_bound_fits_a_bernoulli_rate():
    """Two probabilities start on the bounds 0 and 1 (logit infinite there) and reach the known MLEs 0.03 and 0.95.

    The loss is the Bernoulli negative log-likelihood ``-(k log p + (n - k) log(1 - p))`` with k / n = 0.03
    and 0.95; starting on a bound, a logit variable starts 1e-6 inside (finite gradient).
    """
    rate = np.array([0.03, 0.95])
    k = mi.Float(rate.astype(np.float32))
    variable = FitVariable("p", np.array([0.0, 1.0]), lower=0.0, upper=1.0, scale=1.0, transform="logit")
    assert 0.0 < variable.initial[0] <= 1e-6 and 1.0 - 1e-6 <= variable.initial[1] < 1.0

    def objective(values, step):
        p = values()["p"]
        loss = -dr.sum(k * dr.log(p) + (1.0 - k) * dr.log(1.0 - p))
        dr.backward(loss)
        return float(loss[0])

    fit = adam_fit([variable], objective, 300)
    np.testing.assert_allclose(fit.values["p"], rate, atol=2e-3)


def test_a_variable_the_loss_does_not_read_keeps_its_value():
    """A fit of two variables whose loss reads only ``x``: ``y`` gets no gradient, so it must stay where it
    starts (the fitter's chain through ``T^-1`` raised "does not depend on the input variables" there)."""
    variables = [FitVariable("x", np.array([0.0]), scale=0.1), FitVariable("y", np.array([0.3]), scale=0.1)]
    fit = adam_fit(variables, quadratic(2.0), 30)
    assert fit.values["y"][0] == np.float32(0.3) and fit.values["x"][0] > 0.3  # x moves about 0.5 in 30 steps
