"""Compact trace records give the pass-through mixture, ray for ray, on every evaluation path.

The reference is the mixture evaluated the plain way, in this file: one lane per ray and round at
full width, each element's segment taken from Mitsuba's intersection, the sums folded in numpy
(:func:`full_width_log_likelihood`). The compact path must agree
within float32 rounding whether the segments come from geometry
computed once (``cached``) or are rebuilt along the rays, and whether the rounds come straight from
the trace or are cut from a :class:`RayCache` for a random batch with repeated rays. The tolerance,
1e-3 nats + 1e-5 relative, covers the triangle range recomputed from the plane of the face
(``dot(v0 - o, n) / dot(d, n)``) instead of from the hit point: the two differ by ~1e-5 m at 10 m
in float32, which moves a log density by ``|z - r| 1e-5 / sigma^2`` (< 5e-4 nats at sigma = 2 cm).
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import mixture_log_likelihood
from mi_lidar.core.rays import LogRays
from mi_lidar.core.segment import log_density
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.trace import RESTART_OFFSET, RayCache, cache_distributions, next_intersection, trace_rounds
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, pattern, sensor_pose, shrubs

EFFECTS = (
    "outliers(p_near=0.02, p_uniform=0.01), range_noise(sigma0=0.01), beam_offsets(elevation=[0.002 -0.001]), "
    "range_bias(bias=[0.004 -0.003]), range_scale(scale=1.002)"
)


def full_width_log_likelihood(scene, table, model, rays, z, hit) -> np.ndarray:
    """The mixture the plain way: every ray in every round, sums folded in numpy (float64)."""
    rays = model.prepare_rays(rays)
    hit_np = np.asarray(hit)
    log_mix = np.full(rays.width, -np.inf)
    log_pass = np.zeros(rays.width)

    def fold(valid, p, log_f):
        nonlocal log_mix, log_pass
        valid, p, log_f = np.asarray(valid), np.asarray(p, np.float64), np.asarray(log_f, np.float64)
        term = np.where(valid, log_pass + np.log(np.clip(p, 1e-12, 1)) + log_f, -np.inf)
        log_mix = np.logaddexp(log_mix, term)
        log_pass = log_pass + np.where(valid, np.log(np.clip(1 - p, 1e-12, 1)), 0.0)

    for seg in model.virtual_segments(rays):
        seg = model.segment_law(seg, rays, virtual=True)
        fold(seg.valid, seg.p, log_density(seg, z))
    start = mi.Point3f(rays.origin)
    for _ in range(model.max_segments):
        si, valid, element = next_intersection(scene, table, start, rays.origin, rays.direction, model.max_range)
        seg = model.segment_law(
            table.traced_segment(si, valid, element, rays.origin, rays.direction, model.range_sigma), rays
        )
        fold(seg.valid, seg.p, model.density.log_prob(seg, z, rays))
        start = dr.select(valid, si.p + RESTART_OFFSET * rays.direction, start)
    return np.where(hit_np, log_mix, log_pass)


@pytest.fixture(scope="module")
def problem():
    sets = {"terrain": bowl(p_hit=0.7), "shrubs": shrubs([0.3, 0.5, 0.4, 0.6, 0.2, 0.45])}
    scene = mi_lidar.load_scene(scene_dict(sets))
    model = SensorModel(range_sigma=0.02, max_segments=6, effects=parse_effects(EFFECTS))
    log = mi_lidar.simulate(scene, pattern(200), poses=sensor_pose(0.2, 0.1, 0.3), seed=4, model=model)
    rays = LogRays.from_log(log)
    batch, z, hit = rays.batch(np.arange(rays.n))
    reference = full_width_log_likelihood(scene, ElementTable.from_scene(scene), model, batch, z, hit)
    return scene, model, rays, reference


def assert_close(actual, expected):
    actual = np.asarray(actual, np.float64)
    both = np.isfinite(expected)
    assert np.array_equal(np.isfinite(actual), both)
    np.testing.assert_allclose(actual[both], expected[both], atol=1e-3, rtol=1e-5)


@pytest.mark.parametrize("cached", [False, True], ids=["rebuilt", "cached"])
def test_compact_rounds_match_full_width_likelihood(problem, cached):
    scene, model, rays, reference = problem
    table = ElementTable.from_scene(scene)
    batch, z, hit = rays.batch(np.arange(rays.n))
    rounds = trace_rounds(scene, table, model, batch)
    assert 1 < len(rounds.rounds) <= model.max_segments
    assert rounds.entries < rays.n * len(rounds.rounds)  # compact: fewer entries than full-width lanes
    if cached:
        rounds = cache_distributions(rounds, table, model, batch)
    assert_close(mixture_log_likelihood(table, model, batch, rounds, z, hit), reference)


def test_cache_cuts_any_batch(problem):
    scene, model, rays, reference = problem
    table = ElementTable.from_scene(scene)
    everything, _, _ = rays.batch(np.arange(rays.n))
    cache = RayCache.from_rounds(
        cache_distributions(trace_rounds(scene, table, model, everything), table, model, everything)
    )
    assert cache.n == rays.n and cache.count.max() > 1
    position = np.random.default_rng(0).integers(0, rays.n, 5000)  # with repeats
    batch, z, hit = rays.batch(position)
    for records in (cache.select(position), cache.batch(position)):  # round by round, and ray by ray
        assert_close(mixture_log_likelihood(table, model, batch, records, z, hit), reference[position])
