"""Compact trace records give the core's likelihood, ray for ray, on every evaluation path.

The reference is :meth:`SensorModel.log_likelihood` on the core's full-width trace
(:meth:`SensorModel.trace_segments`, one lane per ray and round). The compact path must agree
within float32 rounding whether the segments come from geometry
computed once (``cached``) or are rebuilt along the rays, and whether the rounds come straight from
the trace or are cut from a :class:`RayCache` for a random batch with repeated rays. The tolerance,
1e-3 nats + 1e-5 relative, covers the triangle range recomputed from the plane of the face
(``dot(v0 - o, n) / dot(d, n)``) instead of from the hit point: the two differ by ~1e-5 m at 10 m
in float32, which moves a log density by ``|z - r| 1e-5 / sigma^2`` (< 5e-4 nats at sigma = 2 cm).
"""

import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.differentiable import DiffTable, LogRays
from mi_lidar.calibration.likelihood import mixture_log_likelihood
from mi_lidar.calibration.records import RayCache, cache_distributions, trace_rounds
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, pattern, sensor_pose, shrubs

EFFECTS = (
    "outliers(p_near=0.02, p_uniform=0.01), range_noise(sigma0=0.01), beam_offsets(elevation=[0.002 -0.001]), "
    "range_bias(bias=[0.004 -0.003]), range_scale(scale=1.002)"
)


@pytest.fixture(scope="module")
def problem():
    sets = {"terrain": bowl(p_hit=0.7), "shrubs": shrubs([0.3, 0.5, 0.4, 0.6, 0.2, 0.45])}
    scene = mi_lidar.load_scene(scene_dict(sets))
    model = SensorModel(range_sigma=0.02, max_segments=6, effects=parse_effects(EFFECTS))
    log = mi_lidar.simulate(scene, pattern(200), poses=sensor_pose(0.2, 0.1, 0.3), seed=4, model=model)
    rays = LogRays.from_log(log)
    batch, z, hit = rays.batch(np.arange(rays.n))
    reference = model.log_likelihood(
        ElementTable.from_scene(scene),
        batch,
        model.trace_segments(scene, ElementTable.from_scene(scene), batch),
        z,
        hit,
    )
    return scene, model, rays, np.asarray(reference, np.float64)


def assert_close(actual, expected):
    actual = np.asarray(actual, np.float64)
    both = np.isfinite(expected)
    assert np.array_equal(np.isfinite(actual), both)
    np.testing.assert_allclose(actual[both], expected[both], atol=1e-3, rtol=1e-5)


@pytest.mark.parametrize("cached", [False, True], ids=["rebuilt", "cached"])
def test_compact_rounds_match_full_width_likelihood(problem, cached):
    scene, model, rays, reference = problem
    table = DiffTable.from_scene(scene)
    batch, z, hit = rays.batch(np.arange(rays.n))
    rounds = trace_rounds(scene, table, model, batch)
    assert 1 < len(rounds.rounds) <= model.max_segments
    assert rounds.entries < rays.n * len(rounds.rounds)  # compact: fewer entries than full-width lanes
    if cached:
        rounds = cache_distributions(rounds, table, model, batch)
    assert_close(mixture_log_likelihood(table, model, batch, rounds, z, hit), reference)


def test_cache_cuts_any_batch(problem):
    scene, model, rays, reference = problem
    table = DiffTable.from_scene(scene)
    everything, _, _ = rays.batch(np.arange(rays.n))
    cache = RayCache.from_rounds(
        cache_distributions(trace_rounds(scene, table, model, everything), table, model, everything)
    )
    assert cache.n == rays.n and cache.count.max() > 1
    position = np.random.default_rng(0).integers(0, rays.n, 5000)  # with repeats
    batch, z, hit = rays.batch(position)
    for records in (cache.select(position), cache.batch(position)):  # round by round, and ray by ray
        assert_close(mixture_log_likelihood(table, model, batch, records, z, hit), reference[position])
