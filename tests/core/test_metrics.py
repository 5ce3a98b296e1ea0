"""Observation-level losses: Chamfer distance, sample metrics with rays, and the realism guard."""

import numpy as np
import pytest

from mi_lidar.core.metrics import chamfer, metrics_of, worse_samples


def test_chamfer_of_a_shifted_cloud_is_the_shift_and_empty_is_nan():
    a = np.random.default_rng(0).uniform(0, 10, (500, 3)) * [1, 1, 0]  # points on a plane
    assert chamfer(a, a + [0, 0, 0.1]) == pytest.approx(0.1)
    assert chamfer(a, a) == 0.0
    assert np.isnan(chamfer(a, np.zeros((0, 3))))


def test_metrics_with_rays_add_the_chamfer_of_measured_and_sampled_points():
    n = 200
    directions = np.tile([1.0, 0.0, 0.0], (n, 1))
    origins = np.stack([np.zeros(n), np.arange(n) * 0.5, np.zeros(n)], 1)
    measured, sampled = np.full(n, 10.0), np.full(n, 10.2)
    hit = np.ones(n, bool)
    row = metrics_of(np.zeros(n), measured, hit, sampled, hit, origins, directions)
    assert row["chamfer"] == pytest.approx(0.2) and row["range_error_median"] == pytest.approx(0.2)
    assert row["stray"] == pytest.approx(0.2)
    stray = sampled.copy()
    stray[::20] = 40.0  # 5 % of the sampled returns drawn far from any measured point
    row = metrics_of(np.zeros(n), measured, hit, stray, hit, origins, directions)
    assert row["stray"] > 1.0 and row["range_error_median"] == pytest.approx(0.2)  # the paired median does not see them
    assert "chamfer" not in metrics_of(np.zeros(n), measured, hit, sampled, hit)


def test_worse_samples_flags_realism_that_got_worse_beyond_the_tolerance():
    before = {"histogram_l1": 0.25, "f1": 0.90, "chamfer": 0.30, "stray": 0.3, "range_error_median": 0.05}
    assert worse_samples(before, {**before, "histogram_l1": 0.27, "f1": 0.85}) == {}  # within 10 %
    flagged = worse_samples(before, {**before, "histogram_l1": 2.28, "f1": 0.70, "range_error_median": 1.0})
    assert flagged == {"histogram_l1": (0.25, 2.28), "f1": (0.90, 0.70)}  # the paired error is not judged by default
    assert worse_samples(before, {**before, "range_error_median": 1.0}, keys=("range_error_median",))
