"""Fitting at parameter bounds: projected steps, and noise scales that can leave zero."""

from __future__ import annotations

import dataclasses

import numpy as np

from mi_lidar.core.effects import make_effect
from mi_lidar.core.problem import Problem, fit_parts
from mi_lidar.core.rays import LogRays

from .helpers import hidden_log, room


def test_range_noise_started_at_zero_grows_to_the_true_sigma():
    """sigma = sigma0 + k r has zero gradient at sigma0 = k = 0; the fit must still leave that point.

    Truth: constant 4 cm noise on the room scene (12 scans x 360 beams). Started at the effect's
    identity (both 0), the fitted sigma0 must come within 0.5 cm of 4 cm (fixed seed).
    """
    scene, model, poses = room(n_scans=12)
    log, _ = hidden_log(scene, model, poses, "range_noise(sigma0=0.04)")
    effect = make_effect("range_noise", law="proportional")
    fitted = dataclasses.replace(model, effects=model.effects + [effect])
    rays = LogRays.from_log(log)
    fit_parts(fitted, Problem.build(scene, rays, np.arange(rays.n)), [effect], steps=150)
    sigma0, k = float(np.asarray(effect.params["sigma0"])[0]), float(np.asarray(effect.params["k"])[0])
    assert abs(sigma0 + k * 3.0 - 0.04) < 0.005  # sigma at the room's typical 3 m range


def test_fitted_values_stay_within_their_bounds():
    """A dropout probability whose data want it below 0 ends exactly at its lower bound 0, not beyond."""
    scene, model, poses = room(n_scans=6)
    log, _ = hidden_log(scene, model, poses, "range_noise(sigma0=0.02)")
    effect = make_effect("random_dropout", p_drop=0.05)
    fitted = dataclasses.replace(model, effects=model.effects + [make_effect("range_noise", sigma0=0.02), effect])
    rays = LogRays.from_log(log)
    fit_parts(fitted, Problem.build(scene, rays, np.arange(rays.n)), [effect], steps=100)
    p = float(np.asarray(effect.params["p_drop"])[0])
    assert 0.0 <= p < 0.005


def test_a_refit_with_one_more_effect_never_ends_worse_than_its_start():
    """Adding an effect at its identity and refitting jointly keeps the training log-likelihood (to 1e-6 nats/ray)."""
    scene, model, poses = room(n_scans=6)
    log, _ = hidden_log(scene, model, poses, "range_noise(sigma0=0.03)")
    rays = LogRays.from_log(log)
    problem = Problem.build(scene, rays, np.arange(rays.n))
    fitted = dataclasses.replace(model, effects=model.effects + [make_effect("range_noise", sigma0=0.01)])
    fit_parts(fitted, problem, steps=60)
    before = float(problem.log_likelihood(fitted).mean())
    fitted.effects = fitted.effects + [make_effect("random_dropout", p_drop=0.0)]
    history = fit_parts(fitted, problem, steps=5, lr=3.0).history
    after = float(problem.log_likelihood(fitted).mean())
    assert after >= before - 1e-6
    assert min(history) < max(history)  # 3 scales per step overshoots: without the best-seen restore this ends worse
