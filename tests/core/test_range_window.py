"""The sensor's range window: a return drawn beyond ``max_range`` (or inside ``min_range``) is not reported.

A wall 2 sigma short of the maximum range (9.98 m, sigma 1 cm, max 10 m) returns beyond the window with
probability 1 - Phi(2) = 2.275 %. The sampler must drop those draws and the likelihood must give a miss
exactly that probability (before, a miss there scored the 1e-9 floor: 20.7 nats), while a return inside
the window keeps its unnormalised Gaussian density. 200,000 identical rays, seed 3: the sampled miss rate
has a binomial standard deviation of 0.033 %; the tolerance is 0.15 % (4.5 standard deviations).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.densities import BeamDensity, ElementGaussian
from mi_lidar.core.densities.base import escape_segment
from mi_lidar.core.densities.physics import PhysicsDensity
from mi_lidar.core.effects import make_effect
from mi_lidar.core.likelihood import FLOOR, RESOLUTION
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.core.segment import ELLIPSOID, SURFACE
from mi_lidar.scene import scene_sensor_model

WALL, SIGMA, MAX_RANGE = 9.98, 0.01, 10.0
BEAMS, SCANS = 500, 400
P_BEYOND = 0.5 * math.erfc(2.0 / math.sqrt(2.0))  # 1 - Phi(2)


def wall_scene(tmp_path, min_range: float = 0.0, wall: float = WALL, max_range: float = MAX_RANGE):
    """A wall facing a planar scanner whose ``BEAMS`` beams all fire straight at it, ``wall`` m away."""
    rows = [f"{i},0,0.0,0.0,{1e-4 * i:.6f}" for i in range(BEAMS)]
    table = tmp_path / "beams.csv"
    table.write_text("row,col,elevation_deg,azimuth_deg,time_s\n" + "\n".join(rows) + "\n")
    xml = tmp_path / "wall.xml"
    xml.write_text(
        '<scene version="3.0.0"><integrator type="lidar_integrator"/>'
        f'<sensor type="lidar"><string name="pattern" value="{table}"/>'
        f'<float name="max_range" value="{max_range}"/><float name="min_range" value="{min_range}"/>'
        f'<float name="range_sigma" value="{SIGMA}"/></sensor>'
        '<shape type="rectangle"><transform name="to_world"><scale x="2" y="2"/><rotate y="1" angle="-90"/>'
        f'<translate x="{wall}"/></transform></shape></scene>'
    )
    return mi_lidar.load_scene(xml)


def simulated(scene, seed: int = 3):
    poses = np.tile(np.eye(4), (SCANS, 1, 1))
    return mi_lidar.simulate(scene, poses=poses, seed=seed)


def test_draws_beyond_the_maximum_range_are_misses_in_the_sampler_and_the_likelihood(tmp_path):
    scene = wall_scene(tmp_path)
    log = simulated(scene)
    hit = log.hit.ravel()
    ranges = log.ranges.ravel()[hit]
    assert ranges.max() <= MAX_RANGE
    assert abs((1.0 - hit.mean()) - P_BEYOND) < 0.0015, 1.0 - hit.mean()

    model, _ = scene_sensor_model(scene)
    ll = Problem.build(scene, LogRays.from_log(log)).log_likelihood(model)
    assert np.allclose(ll[~hit], math.log(P_BEYOND + FLOOR), atol=2e-3), ll[~hit][:3]
    z = ranges[:1000]
    gaussian = np.exp(-0.5 * ((z - WALL) / SIGMA) ** 2) / (SIGMA * math.sqrt(2 * math.pi))
    assert np.allclose(ll[hit][:1000], np.log(gaussian * RESOLUTION + FLOOR), atol=2e-3)


def test_draws_inside_the_minimum_range_are_misses_as_well(tmp_path):
    """The blind zone is the other end of the window: with min_range 2 sigma short of the wall as well,
    both tails are cut (binomial standard deviation 0.047 %)."""
    scene = wall_scene(tmp_path, min_range=WALL - 2 * SIGMA)
    log = simulated(scene)
    hit = log.hit.ravel()
    ranges = log.ranges.ravel()[hit]
    assert ranges.min() >= WALL - 2 * SIGMA and ranges.max() <= MAX_RANGE
    assert abs((1.0 - hit.mean()) - 2 * P_BEYOND) < 0.002, 1.0 - hit.mean()
    model, _ = scene_sensor_model(scene)
    ll = Problem.build(scene, LogRays.from_log(log)).log_likelihood(model)
    assert np.allclose(ll[~hit], math.log(2 * P_BEYOND + FLOOR), atol=2e-3)


@pytest.mark.parametrize("scale", [1.0005, 1.002])
def test_the_window_gradient_matches_finite_differences(tmp_path, scale):
    """d(summed score)/d(range_scale.scale) where the scale moves the law across the maximum range.

    Central difference of step 1e-5 on float64 sums of float32 per-ray values; tolerance 2 % of the
    larger of the two plus 50 nats per unit of scale (the difference's own float32 noise)."""
    scene = wall_scene(tmp_path)
    log = simulated(scene)
    model, _ = scene_sensor_model(scene)
    effect = make_effect("range_scale", scale=scale)
    model.effects = [effect]
    problem = Problem.build(scene, LogRays.from_log(log))
    problem.trace(model)

    def total(x: float, grad: bool = False) -> float:
        param = mi.Float([x])
        if grad:
            dr.enable_grad(param)
        effect.params["scale"] = param
        ll = problem.chunk_log_likelihood(model, problem.chunks[0])
        if grad:
            dr.backward(dr.sum(ll))
            return float(dr.grad(param)[0])
        return float(np.sum(np.asarray(ll, np.float64)))

    h = 1e-5
    auto = total(scale, grad=True)
    numeric = (total(scale + h) - total(scale - h)) / (2 * h)
    assert abs(auto - numeric) <= 0.02 * max(abs(auto), abs(numeric)) + 50.0, (auto, numeric)


def _lanes(density, r: float, n: int, **fields):
    from ..conftest import rays_along_x

    rays = rays_along_x(n)
    at = dr.full(mi.Float, r, n)
    seg = escape_segment(rays).with_(kind=dr.full(mi.UInt32, SURFACE, n), nominal=at, mean=at)
    seg = seg.with_(**{k: dr.full(type(v) if not isinstance(v, float) else mi.Float, v, n) for k, v in fields.items()})
    return density.prepare(seg, rays), rays


def _families():
    from .test_np_reg_support import density as np_reg

    return {
        "np_reg-histogram": (np_reg("histogram"), {}),
        "np_reg-polygon": (np_reg("polygon"), {"sigma": 0.05}),
        "beam": (BeamDensity(sigma=0.07), {}),
        "gaussian-ellipsoid": (ElementGaussian(), {"sigma": 0.1, "lo": 4.85, "hi": 5.3, "kind": ELLIPSOID}),
        "physics": (PhysicsDensity(), {}),
    }


@pytest.mark.parametrize("family", sorted(_families()))
@pytest.mark.parametrize("window", [(0.0, 5.02), (4.99, 40.0), (2.5, 4.99), (0.0, math.inf)])
def test_each_family_window_is_the_integral_of_its_density(family, window):
    """``window(a, b)`` of every return family equals the integral of ``exp(log_prob)`` over [a, b] at a
    nominal range of 5 m (midpoint rule, 0.5 mm steps; tolerance 2e-3, the quadrature's error on 1 cm bins). An
    open window is integrated to 100 m, beyond every family's support here (NP-Reg's and the beam model's z_max)."""
    density, fields = _families()[family]
    a, b = window
    step = 5e-4
    z = np.arange(a + step / 2, min(b, 100.0), step)
    seg, rays = _lanes(density, 5.0, z.size, **fields)
    f = np.exp(np.asarray(density.log_prob(seg, mi.Float(z.astype(np.float32)), rays), np.float64))
    seg1, rays1 = _lanes(density, 5.0, 1, **fields)
    value = float(np.asarray(density.window(seg1, a, b, rays1))[0])
    assert abs(value - f.sum() * step) < 2e-3, (value, f.sum() * step)


def test_random_returns_stay_inside_the_window(tmp_path):
    """Virtual elements stand for returns the sensor reports: outliers uniform on [0, 80 m] behind a 10 m
    window are drawn on [0, 10 m], so they never stand in for a dropout. A miss then has probability
    (1 - p_uniform) (1 - Phi(2)) = 1.82 % (left whole, 0.2 x 7/8 of the draws would be lost as well: 19.3 %);
    same tolerance as above."""
    scene = wall_scene(tmp_path)
    model, _ = scene_sensor_model(scene)
    model.effects = [make_effect("outliers", p_uniform=0.2, uniform_max=80.0)]
    poses = np.tile(np.eye(4), (SCANS, 1, 1))
    log = mi_lidar.simulate(scene, poses=poses, seed=3, model=model)
    hit = log.hit.ravel()
    expected = 0.8 * P_BEYOND
    assert log.ranges.ravel()[hit].max() <= MAX_RANGE
    assert abs((1.0 - hit.mean()) - expected) < 0.0015, 1.0 - hit.mean()
    ll = Problem.build(scene, LogRays.from_log(log)).log_likelihood(model)
    assert np.allclose(ll[~hit], math.log(expected + FLOOR), atol=2e-3), ll[~hit][:3]


@pytest.mark.parametrize(
    "effect", ["mixed_pixels(divergence=0.003, share=0.5)", "multiple_returns(mode=last, divergence=0.003)"]
)
def test_beams_with_a_footprint_see_the_window_once_combined(tmp_path, effect):
    """A footprint effect fans each beam into five sub-rays; at a wall 2 sigma short of the maximum range
    (the outer sub-rays 0.04 mm farther) the combined return lies beyond the window with probability
    1 - Phi(2) as well. The sampler drops it; the likelihood must give a miss that probability (before, the
    floor), and a return the density it gave before (the window only moves mass to the miss).
    Same rays, seed and sampling tolerance as above; the likelihood's miss within 0.02 nats (2 % of the
    probability; measured 0.006 and 0.010): the likelihood approximates the combined law from the sub-rays'
    moments (an average of the sub-rays' variances for the mixed pixel, a smoothed order for the last echo)."""
    from mi_lidar.core.effects import parse_effects

    scene = wall_scene(tmp_path)
    model, _ = scene_sensor_model(scene)
    model.effects = parse_effects(effect)
    poses = np.tile(np.eye(4), (SCANS, 1, 1))
    log = mi_lidar.simulate(scene, poses=poses, seed=3, model=model)
    hit = log.hit.ravel()
    assert log.ranges.ravel()[hit].max() <= MAX_RANGE
    assert abs((1.0 - hit.mean()) - P_BEYOND) < 0.0015, 1.0 - hit.mean()
    problem = Problem.build(scene, LogRays.from_log(log))
    ll = problem.log_likelihood(model)
    assert np.allclose(ll[~hit], math.log(P_BEYOND + FLOOR), atol=0.02), ll[~hit][:3]
    model.max_range = math.inf  # an open window: the returns score as before
    assert np.allclose(problem.log_likelihood(model)[hit], ll[hit], atol=1e-5)
