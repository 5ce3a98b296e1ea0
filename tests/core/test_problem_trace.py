"""A split's rays are built once, however often the split is traced again."""

import dataclasses

import numpy as np
import pytest

from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.loop.catalog import candidate
from mi_lidar.scene.simulation import simulate
from tests.loop.helpers import room


def test_tracing_again_under_moved_beams_builds_the_rays_once_and_scores_as_before():
    """Beam offsets move the rays, so every new value traces the split again (a fit of them does every 10 steps,
    the beam-by-beam search at every grid point: 67 traces per screening fit on the sweep's 20,000 fitting rays).
    Each trace used to build the rays from the log anew (LogRays.batch: 9 ms per trace there); now the split's
    rays are built once, and the scores under each model are those of a split traced for that model alone.
    Fails on the parent: 3 builds."""
    scene, model, poses = room(4)
    log = simulate(scene, poses=poses, model=model, seed=2)
    rays = LogRays.from_log(log, scene=scene)
    moved = dataclasses.replace(model, effects=[candidate("beam_offsets", 360, 1, azimuth=0.01)])
    problem = Problem.build(scene, rays)
    built, build = [], rays.batch
    rays.batch = lambda index=None: built.append(index) or build(index)
    scores = [problem.log_likelihood(m) for m in (model, moved, model)]
    assert len(built) == 1
    np.testing.assert_array_equal(scores[2], scores[0])
    np.testing.assert_array_equal(
        scores[1], Problem.build(scene, LogRays.from_log(log, scene=scene)).log_likelihood(moved)
    )
    assert not np.array_equal(scores[1], scores[0])


def test_a_problem_another_tracer_traced_has_no_log_rays_to_judge_by_beam():
    """A planar benchmark's problem (its segments from the ray march, no log rays) cannot sum its rays' scores by
    beam: the error says why instead of an AttributeError on None."""
    from mi_lidar.core.densities import PhysicsDensity
    from mi_lidar.core.errors import ParameterError
    from mi_lidar.planar.beams import base_model, nominal_beams
    from tests.planar.test_backstops import leaky_wall_trace

    problem = nominal_beams(leaky_wall_trace()).problem()
    model = base_model(PhysicsDensity())
    assert np.isfinite(problem.log_likelihood(model)).all()
    with pytest.raises(ParameterError, match="traced by another tracer: it holds no log rays"):
        problem.log_likelihood_by_beam(model, 4)
