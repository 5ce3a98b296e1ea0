"""range_dropout: keep probability exp(-rate (r/10 m)^power) and its recovery."""

import numpy as np
import pytest

from .loop.helpers import assert_keep_law, hidden_log, mean_ll, recover, room


def test_keep_fraction_follows_law():
    """Rate at which the first element returns, per range bin matches exp(-rate (r/10)^power) within 3 binomial sigma +
    0.02."""
    scene, model, poses = room(20)
    assert_keep_law(
        scene,
        model,
        poses,
        "range_dropout(rate=2, power=1)",
        "range_dropout(rate=0)",
        "nominal_range",
        ((0.5, 1.5), (3, 4), (6, 8)),
        lambda r: np.exp(-2 * r / 10),
    )


@pytest.mark.slow
def test_recovers_rate_and_power():
    """rate = 0.3 and power = 1.5 come back within 30 %; NLL within 0.5 % of the true model's."""
    scene, model, poses = room(30)
    log, true = hidden_log(scene, model, poses, "range_dropout(rate=0.3, power=1.5)")
    effect, fitted = recover(scene, model, log, "range_dropout", steps=200)
    assert abs(float(np.asarray(effect["rate"])[0]) - 0.3) < 0.09
    assert abs(float(np.asarray(effect["power"])[0]) - 1.5) < 0.45
    assert mean_ll(scene, fitted, log) > mean_ll(scene, true, log) - 0.005 * abs(mean_ll(scene, true, log))
