"""outliers: near-clutter and uniform random returns as virtual elements, and their recovery."""

import numpy as np
import pytest

from .loop.helpers import hidden_log, mean_ll, recover, room


def test_outlier_rates_and_ranges():
    """5 % near returns (half-normal, scale 1 m) and 3 % uniform ones on [0, 30] m, +- 1 %."""
    scene, model, poses = room(40)
    log, _ = hidden_log(scene, model, poses, "outliers(p_near=0.05, near_scale=1, p_uniform=0.03, uniform_max=30)")
    clean, _ = hidden_log(scene, model, poses, "outliers(p_near=0, p_uniform=0)")
    moved = log.hit & (np.abs(log.ranges - np.nan_to_num(clean.ranges)) > 0.1)
    assert abs(moved.mean() - 0.075) < 0.01
    far = log.hit & (log.ranges > 12)  # beyond the room: only uniform outliers
    assert abs(far.mean() - 0.03 * 18 / 30 * 0.95) < 0.006


@pytest.mark.slow
def test_recovers_outlier_parameters():
    scene, model, poses = room(30)
    log, true = hidden_log(scene, model, poses, "outliers(p_near=0.05, near_scale=1, p_uniform=0.03, uniform_max=30)")
    effect, fitted = recover(scene, model, log, "outliers", uniform_max=30)
    assert abs(float(np.asarray(effect["p_near"])[0]) - 0.05) < 0.01
    assert abs(float(np.asarray(effect["near_scale"])[0]) - 1.0) < 0.15
    assert abs(float(np.asarray(effect["p_uniform"])[0]) - 0.03) < 0.01
    assert mean_ll(scene, fitted, log) > mean_ll(scene, true, log) - 0.01
