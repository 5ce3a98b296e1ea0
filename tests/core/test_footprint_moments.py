"""Footprint effects keep their precision at long range.

The likelihood of a beam fanned out into sub-rays reads each sub-ray's return mean and variance
(``SubRayMoments``). They used to be summed as ``E[z]`` and ``E[z^2]`` and the variance taken as their
difference: at 60 m float32 rounds ``E[z^2]`` (3600 m^2) by 2.4e-4 m^2, more than a 1 cm sigma's square,
so every return scored about -19.6 nats against the plain model's -1.43 (wall at 60 m, sigma 1 cm).

Here the sub-rays diverge by 1e-5 rad, so all of them meet the wall at its distance (within 6e-9 m at
120 m) and the effect must score every beam as the model without it: within 0.01 nats per beam
(measured at most 0.003 at 120 m, the float32 step of a range there being 7.6e-6 m).
"""

from __future__ import annotations

import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.scene import scene_sensor_model

from .test_range_window import wall_scene

EFFECTS = ["mixed_pixels(divergence=1e-5, share=0.5)", "multiple_returns(mode=last, divergence=1e-5)"]


@pytest.mark.parametrize("wall", [60.0, 120.0])
@pytest.mark.parametrize("effect", EFFECTS)
def test_a_narrow_footprint_scores_a_far_wall_as_a_single_ray(tmp_path, wall, effect):
    scene = wall_scene(tmp_path, wall=wall, max_range=1000.0)
    model, _ = scene_sensor_model(scene)
    log = mi_lidar.simulate(scene, poses=np.tile(np.eye(4), (4, 1, 1)), seed=3, model=model)
    assert log.hit.all()
    problem = Problem.build(scene, LogRays.from_log(log))
    single = problem.log_likelihood(model)
    model.effects = parse_effects(effect)
    fanned = problem.log_likelihood(model)
    assert np.abs(fanned - single).max() < 0.01, (single.mean(), fanned.mean())
