import numpy as np

from mi_lidar.hybrid.evaluate import observation_metrics, pcd_error
from mi_lidar.hybrid.fit import hit_probability
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh, HybridModel
from mi_lidar.hybrid.raycast import ModelTracer, count_hits, simulate_rays
from mi_lidar.hybrid.baselines import NeighborSimulator


def _two_walls(p_front):
    """Walls x = 5 (p_hit = p_front) and x = 10 (opaque), 20 m wide, sigma 0."""
    quad = lambda x: (np.array([[x, -10, -10], [x, 10, -10], [x, 10, 10], [x, -10, 10]]), np.array([[0, 1, 2], [0, 2, 3]]))
    (v1, f1), (v2, f2) = quad(5.0), quad(10.0)
    g = GroundMesh(np.r_[v1, v2], np.r_[f1, f2 + 4], p_hit=[p_front, p_front, 1, 1], range_sigma=0.0)
    return HybridModel(g, EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3))))


def _rays(n, rng):
    d = np.c_[np.ones(n), rng.uniform(-0.3, 0.3, (n, 2))]
    return np.zeros((n, 3)), d / np.linalg.norm(d, axis=1, keepdims=True)


def test_pass_through_fraction_matches_p_hit(rng):
    tracer = ModelTracer(_two_walls(0.3))
    o, d = _rays(20000, rng)
    r, _ = simulate_rays(tracer, o, d, rng)
    front = np.isclose(r * d[:, 0], 5.0, atol=1e-3)
    # binomial sd = sqrt(0.3 * 0.7 / 20000) = 0.0032; tolerance 4 sd
    assert abs(front.mean() - 0.3) < 0.013
    assert np.all(np.isfinite(r))


def test_counts_recover_p_hit_from_simulated_log(rng):
    model = _two_walls(0.3)
    tracer = ModelTracer(model)
    o, d = _rays(20000, rng)
    r, _ = simulate_rays(tracer, o, d, rng)
    c = count_hits(tracer, o, d, r, np.full(len(r), -1), max_residual=0.5)
    p = hit_probability(c.tri_hits[:2].sum(), c.tri_pass[:2].sum(), (1, 2))
    assert abs(p - 0.3) < 0.013  # same binomial tolerance as above
    assert c.tri_pass[2:].sum() == 0 and np.all(np.abs(c.residuals) < 1e-3)


def test_ellipsoid_return_follows_gaussian_along_ray(rng):
    ell = EllipsoidSet([[10.0, 0, 0]], [np.diag([0.5**2, 0.2**2, 0.2**2])], p_hit=1.0)
    tracer = ModelTracer(HybridModel(GroundMesh(np.zeros((0, 3)), np.zeros((0, 3))), ell, extent=3.0))
    n = 20000
    o, d = np.zeros((n, 3)), np.tile([1.0, 0, 0], (n, 1))
    r, label = simulate_rays(tracer, o, d, rng)
    # mean 10 m, sd 0.5 m; tolerances are 5 standard errors
    assert abs(np.mean(r) - 10) < 5 * 0.5 / np.sqrt(n) and abs(np.std(r) - 0.5) < 0.02


def test_observation_metrics_by_hand():
    real = np.array([[[10.0, np.nan, 5.0, 7.0]]])
    sim = np.array([[[11.0, 3.0, np.nan, 7.5]]])
    o = np.zeros((4, 3))
    d = np.tile([1.0, 0, 0], (4, 1))
    m = observation_metrics(real, sim, o, d, packet=2)
    assert m["true_hits"] == 2 and m["false_hits"] == 1 and m["false_misses"] == 1
    assert np.isclose(m["precision"], 2 / 3) and np.isclose(m["recall"], 2 / 3)
    assert np.isclose(m["packet_error"], (1.0 + 0.5) / 2)  # packet 1: |10-11|, packet 2: |7-7.5|


def test_pcd_error_symmetric_definition():
    y = np.array([[0.0, 0, 0], [1, 0, 0]])
    y_hat = np.array([[0.0, 0, 0.5]])
    assert np.isclose(pcd_error(y, y_hat), 0.5 * (0.5 + (0.5 + np.sqrt(1.25)) / 2))


def test_neighbor_simulator_replays_nearest_point_along_ray():
    pts = np.array([[5.0, 0.1, 0], [8.0, 0.0, 0], [3.0, 2.0, 0]])
    sim = NeighborSimulator(pts, d_perp=0.3)
    r = sim.simulate(np.zeros((2, 3)), np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    assert np.isclose(r[0], 5.0, atol=1e-5) and np.isnan(r[1])
