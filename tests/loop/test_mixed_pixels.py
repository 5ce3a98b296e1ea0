"""Mixed pixels (beam divergence): the sampler and the approximate likelihood agree.

In the room every sub-ray meets one opaque wall with Gaussian noise, where the likelihood of
:class:`~mi_lidar.core.effects.mixed_pixels.MixedPixels` is exact: the combined range of each beam is
Gaussian with the mean and variance the likelihood implies. 60 simulated scans (fixed seeds) are
checked against it, and the likelihood's gradient in ``divergence`` against finite differences.
"""

import dataclasses

import numpy as np

from mi_lidar.core.effects import parse_effects
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.scene.simulation import simulate

from .helpers import finite_difference_check, hidden_log, room

SEEDS = 60


def test_sampler_matches_likelihood_moments():
    scene, model, poses = room(1)
    true = dataclasses.replace(model, effects=parse_effects("mixed_pixels(divergence=0.03)"))
    logs = [simulate(scene, poses=poses, model=true, seed=s) for s in range(SEEDS)]
    ranges = np.stack([log.ranges.ravel() for log in logs])
    assert all(log.hit.all() for log in logs)
    mean, var = ranges.mean(0), ranges.var(0, ddof=1)
    # The likelihood's Gaussian, read off three evaluations of its (quadratic) log density.
    rays = LogRays.from_log(logs[0])
    h = 0.01
    ll = []
    for shift in (-h, 0.0, h):
        rays.measured = (mean + shift).astype(np.float32)
        problem = Problem.build(scene, rays, np.arange(rays.n))  # a split reads its measured ranges once
        ll.append(problem.log_likelihood(true))  # scored: a constant 1 cm bin offset, far above the floor
    curvature = (ll[0] - 2 * ll[1] + ll[2]) / h**2
    v = -1.0 / curvature
    mu = mean + v * (ll[2] - ll[0]) / (2 * h)
    z = (mean - mu) / np.sqrt(v / SEEDS)
    # Means agree to sampling error (|median z| < 0.3, 99 % within 3.5), variances to 15 %.
    assert abs(np.median(z)) < 0.3, np.median(z)
    assert np.mean(np.abs(z) < 3.5) > 0.99
    assert abs(np.median(var / v) - 1) < 0.15, np.median(var / v)
    # The divergence mixes walls at the corners: there the combined variance exceeds one wall's.
    assert np.max(v) > 1.5 * np.min(v)


def test_divergence_gradient_matches_finite_difference():
    scene, model, poses = room(2)
    log, true = hidden_log(scene, model, poses, "mixed_pixels(divergence=0.02)")
    effect = true.effects[-1]
    auto, numeric = finite_difference_check(scene, true, log, effect, "divergence", h=1e-3, n_rays=720)
    assert abs(auto - numeric) < 0.05 * abs(numeric) + 1e-2, (auto, numeric)
