"""incidence_dropout: keep probability cos^gamma, recovery by fitting, gradient against finite differences."""

import numpy as np
import pytest

from mi_lidar.core.effects import make_effect, parse_effects

from .loop.helpers import assert_keep_law, finite_difference_check, hidden_log, mean_ll, recover, room


def test_keep_fraction_follows_cos_power():
    """Rate at which the first element returns, per incidence bin matches cos(delta)^gamma within 3 sigma of the
    binomial noise."""
    scene, model, poses = room(20)
    assert_keep_law(
        scene,
        model,
        poses,
        "incidence_dropout(gamma=2)",
        "incidence_dropout(gamma=0)",
        "cos_incidence",
        ((0.9, 1.0), (0.6, 0.7), (0.3, 0.4)),
        lambda cos: cos**2,
    )


@pytest.mark.slow
def test_recovers_gamma():
    """Fitting recovers gamma = 2 within 0.2 and the true model's NLL within 0.5 %."""
    scene, model, poses = room(30)
    log, true = hidden_log(scene, model, poses, "incidence_dropout(gamma=2)")
    effect, fitted = recover(scene, model, log, "incidence_dropout")
    assert abs(float(np.asarray(effect["gamma"])[0]) - 2.0) < 0.2
    assert mean_ll(scene, fitted, log) > mean_ll(scene, true, log) - 0.005 * abs(mean_ll(scene, true, log))


def test_gradient_matches_finite_difference():
    """d(sum log-likelihood)/d(gamma) agrees with a central difference (h = 1e-2) to 2 %."""
    scene, model, poses = room(4)
    log, _ = hidden_log(scene, model, poses, "incidence_dropout(gamma=1.5)")
    trial = parse_effects("incidence_dropout(gamma=1.2)")
    auto, numeric = finite_difference_check(
        scene, model.__class__(**{**model.__dict__, "effects": trial}), log, trial[0], "gamma", 1e-2
    )
    assert auto == pytest.approx(numeric, rel=0.02)


def test_rejects_negative_gamma():
    with pytest.raises(Exception, match="gamma"):
        make_effect("incidence_dropout", gamma=-1)
