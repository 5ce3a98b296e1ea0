"""The hybrid model in the product's core: simulation, element counting, written scenes, metrics."""

import mitsuba as mi
import numpy as np

import mi_lidar
from mi_lidar.core.log import Log
from mi_lidar.core.sensor_model import CHANNELS
from mi_lidar.hybrid.baselines import NeighborSimulator
from mi_lidar.hybrid.blocks import SceneSensor, write_scene
from mi_lidar.hybrid.counting import count_hits
from mi_lidar.hybrid.evaluate import observation_metrics, pcd_error
from mi_lidar.hybrid.fit import FitParams, assign_hit_probabilities, hit_probability, world_rays
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh, HybridModel
from mi_lidar.hybrid.simulation import load_model, simulate_log


def _two_walls(p_front):
    """Walls x = 5 (p_hit = p_front) and x = 10 (opaque), 20 m wide, sigma 0."""
    quad = lambda x: (
        np.array([[x, -10, -10], [x, 10, -10], [x, 10, 10], [x, -10, 10]]),
        np.array([[0, 1, 2], [0, 2, 3]]),
    )
    (v1, f1), (v2, f2) = quad(5.0), quad(10.0)
    g = GroundMesh(np.r_[v1, v2], np.r_[f1, f2 + 4], p_hit=[p_front, p_front, 1, 1], range_sigma=0.0)
    return HybridModel(g, EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))))


def _forward_log(rng, rows=100, cols=200, spread=0.3):
    """One scan of rows x cols rays from the origin, fanned around +x (ranges unset)."""
    d = np.concatenate([np.ones((rows, cols, 1)), rng.uniform(-spread, spread, (rows, cols, 2))], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    shape = (1, rows, cols)
    return Log(
        poses=np.eye(4)[None],
        directions=d[None],
        ranges=np.full(shape, np.nan),
        hit=np.zeros(shape, bool),
        times=np.zeros(shape),
        sensor={"min_range": 1.0, "max_range": 80.0},
    )


def test_core_pass_through_fraction_matches_p_hit(rng):
    log = _forward_log(rng)
    r, label = simulate_log(_two_walls(0.3), log, seed=4)
    x = r * log.directions[..., 0]
    front = np.isclose(x, 5.0, atol=1e-3)
    # binomial sd = sqrt(0.3 * 0.7 / 20000) = 0.0032; tolerance 4 sd
    assert abs(front.mean() - 0.3) < 0.013
    assert np.all(np.isclose(x[~front], 10.0, atol=1e-3)) and np.all(label == 1)


def test_counts_recover_p_hit_from_core_simulation(rng):
    model = _two_walls(0.3)
    log = _forward_log(rng)
    r, _ = simulate_log(model, log, seed=5)
    o, d = world_rays(log)
    c = count_hits(load_model(model), o, d, r.ravel(), np.full(r.size, -1), 4, 0, max_residual=0.5)
    p = hit_probability(c.tri_hits[:2].sum(), c.tri_pass[:2].sum(), (1, 2))
    assert abs(p - 0.3) < 0.013  # same binomial tolerance as above
    assert c.tri_pass[2:].sum() == 0 and np.all(np.abs(c.residuals) < 1e-3) and c.grazing == 0


def test_grazing_crossing_is_neither_hit_nor_pass():
    """A ray crossing a plane at 1 deg returns 2 m behind it (3.5 cm along the normal): not a pass."""
    plane = GroundMesh(
        [[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], [[0, 1, 2], [0, 2, 3]], range_sigma=0.0
    )
    model = HybridModel(plane, EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))))
    steep, grazing = np.deg2rad(30.0), np.deg2rad(1.0)
    d = np.array([[np.cos(steep), 0, -np.sin(steep)], [np.cos(grazing), 0, -np.sin(grazing)]])
    o = np.array([[0, 0, 1.0], [0, 0, 0.1]])
    t = np.array([1 / np.sin(steep), 0.1 / np.sin(grazing)])
    measured = np.array([t[0] + 0.01, t[1] + 2.0])
    c = count_hits(load_model(model), o, d, measured, np.full(2, -1), 2, 0, max_residual=0.75, pass_sigmas=3.0)
    # sigma_normal = RMS over the one hit: 0.01 m * sin(30 deg) = 0.005 m; 2 m * sin(1 deg) = 0.035 m > 3 sigma
    assert np.isclose(c.sigma_normal, 0.005, atol=1e-4)
    assert c.tri_hits.sum() == 1 and c.tri_pass.sum() == 1 and c.grazing == 0
    c = count_hits(load_model(model), o, d, measured, np.full(2, -1), 2, 0, max_residual=0.75, pass_sigmas=10.0)
    assert c.tri_pass.sum() == 0 and c.grazing == 1


def test_ellipsoid_return_follows_gaussian_along_ray(rng):
    ell = EllipsoidSet([[10.0, 0, 0]], [np.diag([0.5**2, 0.2**2, 0.2**2])], p_hit=1.0, label=5)
    model = HybridModel(GroundMesh(np.zeros((0, 3)), np.zeros((0, 3))), ell, extent=3.0)
    log = _forward_log(rng, 100, 200, spread=0.0)
    r, label = simulate_log(model, log, seed=6)
    # mean 10 m, sd 0.5 m truncated at +-3 sd (sd 0.493 m); tolerances are 5 standard errors
    assert abs(np.mean(r) - 10) < 5 * 0.5 / np.sqrt(r.size) and abs(np.std(r) - 0.493) < 0.02
    assert np.all(label == 5)


def test_written_scene_loads_renders_and_matches_log(small_log, small_fit, tmp_path):
    """The fitted scene, written with sensor and integrator, loads and renders with the core.

    Tolerances: the model is fitted to the same log, so its simulated hit fraction lies within
    0.1 of the logged one and the median range error of rays that hit in both is below 0.15 m;
    ``mi.render`` and ``mi_lidar.simulate`` use the same rays and seed and agree to 1 mm on at
    least 95 % of them (float32 directions differ in the last bits between the two paths).
    """
    (tmp_path / "s_assets").mkdir()
    sensor = SceneSensor.from_log(small_log, tmp_path / "s_assets" / "pattern.npy")
    xml, *_ = write_scene(small_fit.model, tmp_path, "s", sensor)
    scene = mi_lidar.load_scene(xml)
    image = np.array(mi.render(scene, seed=3))
    assert image.shape == small_log.shape[1:] + (len(CHANNELS),)
    rendered = np.where(image[..., 1] > 0, image[..., 0], np.nan)
    sim = mi_lidar.simulate(scene, seed=3)
    same = np.isclose(np.nan_to_num(sim.ranges[0], nan=-1), np.nan_to_num(rendered, nan=-1), atol=1e-3)
    assert same.mean() > 0.95
    full = mi_lidar.simulate(scene, poses=small_log.poses, seed=3)
    real = np.where(small_log.hit, small_log.ranges, np.nan)
    assert abs(full.hit.mean() - small_log.hit.mean()) < 0.1
    both = full.hit & small_log.hit
    assert np.median(np.abs(full.ranges[both] - real[both])) < 0.15


def test_observation_metrics_by_hand():
    real = np.array([[[10.0, np.nan, 5.0, 7.0]]])
    sim = np.array([[[11.0, 3.0, np.nan, 7.5]]])
    o = np.zeros((4, 3))
    d = np.tile([1.0, 0, 0], (4, 1))
    m = observation_metrics(real, sim, o, d, packet=2)
    assert m["true_hits"] == 2 and m["false_hits"] == 1 and m["false_misses"] == 1
    assert np.isclose(m["precision"], 2 / 3) and np.isclose(m["recall"], 2 / 3)
    assert np.isclose(m["packet_error"], (1.0 + 0.5) / 2)  # packet 1: |10-11|, packet 2: |7-7.5|
    masked = observation_metrics(real, sim, o, d, packet=2, mask=np.array([[[True, False, False, True]]]))
    assert masked["true_hits"] == 2 and masked["false_hits"] == 0 and masked["false_misses"] == 0


def test_pcd_error_symmetric_definition():
    y = np.array([[0.0, 0, 0], [1, 0, 0]])
    y_hat = np.array([[0.0, 0, 0.5]])
    assert np.isclose(pcd_error(y, y_hat), 0.5 * (0.5 + (0.5 + np.sqrt(1.25)) / 2))


def test_neighbor_simulator_replays_nearest_point_along_ray():
    pts = np.array([[5.0, 0.1, 0], [8.0, 0.0, 0], [3.0, 2.0, 0]])
    sim = NeighborSimulator(pts, d_perp=0.3)
    r = sim.simulate(np.zeros((2, 3)), np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    assert np.isclose(r[0], 5.0, atol=1e-5) and np.isnan(r[1])


def test_pooled_prior_keeps_p_hit_of_sparsely_crossed_triangles(rng):
    """A wall of 800 small triangles with p_hit 0.8, crossed about 25 times each.

    The table 4.1 prior (1, 2) pulls the estimates towards 1/3; the pooled prior keeps their
    mean within 0.02 of 0.8 (the pooled fraction has sd sqrt(0.16 / 20000) = 0.003; a
    triangle's estimate is shrunk towards it).
    """
    grid = np.stack(np.meshgrid(np.linspace(-10, 10, 21), np.linspace(-10, 10, 21), indexing="ij"), -1).reshape(-1, 2)
    vertices = np.c_[np.full(len(grid), 5.0), grid]
    quads = [(i * 21 + j, (i + 1) * 21 + j, (i + 1) * 21 + j + 1, i * 21 + j + 1) for i in range(20) for j in range(20)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    truth = HybridModel(
        GroundMesh(vertices, faces, p_hit=0.8, range_sigma=0.0), EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3)))
    )
    log = _forward_log(rng, 100, 200, spread=1.9)
    log.ranges[:], _ = simulate_log(truth, log, seed=7)
    log.hit = np.isfinite(log.ranges)
    owner = np.full(log.n_rays, -1)
    means = {}
    for strength in (0.0, 3.0):
        model = HybridModel(GroundMesh(vertices, faces), EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))))
        info = assign_hit_probabilities(model, log, owner, FitParams(pooled_strength=strength))
        means[strength] = model.ground.p_hit.mean()
    assert abs(info["pooled_triangle_p_hit"] - 0.8) < 0.012
    assert abs(means[3.0] - 0.8) < 0.02 and means[0.0] < 0.75
