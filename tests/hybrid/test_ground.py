import numpy as np

from mi_lidar.hybrid.classes import GROUND_CLASSES
from mi_lidar.hybrid.ground import (
    GroundParams,
    SurfaceParams,
    WendlandSurface,
    fit_ground_mesh,
    ground_features,
    smooth_variation,
    spherical_variation,
    tune_threshold,
)


def test_spherical_variation_plane_vs_volume(rng):
    plane = np.c_[rng.uniform(0, 5, (2000, 2)), rng.normal(0, 0.005, 2000)]
    blob = rng.normal(0, 1, (2000, 3))
    assert np.median(spherical_variation(plane, 1.0, 20, 10, 0.01)) < 0.01
    assert np.median(spherical_variation(blob, 1.5, 20, 10, 0.01)) > 0.15


def test_too_few_neighbours_get_default(rng):
    far = rng.uniform(0, 1000, (20, 3))
    assert np.all(spherical_variation(far, 0.5, 10, 5, 0.123) == 0.123)


def test_smoothing_is_an_average_that_keeps_constants(rng):
    pts = rng.uniform(0, 3, (500, 3))
    phi = np.full(500, 0.2)
    np.testing.assert_allclose(smooth_variation(pts, phi, 1.0, 1.0, 1.0), 0.2)
    noisy = 0.1 + rng.normal(0, 0.02, 500)
    assert np.std(smooth_variation(pts, noisy, 1.0, 1.0, 0.0)) < np.std(noisy)


def test_segmentation_beats_majority_on_labeled_log(small_log):
    pts = small_log.points_world()[small_log.hit]
    truth = np.isin(small_log.attributes["label"][small_log.hit], GROUND_CLASSES)
    thresh, acc = tune_threshold(ground_features(pts, GroundParams()), truth)
    assert acc > max(truth.mean(), 1 - truth.mean()) + 0.05
    assert 0.005 <= thresh <= 0.2


def test_wendland_surface_fits_smooth_heights(rng):
    xy = rng.uniform(0, 20, (3000, 2))
    f = lambda p: 0.5 * np.sin(p[:, 0] / 3) + 0.1 * p[:, 1]
    surf = WendlandSurface(xy, f(xy), radius=3.0, regularization=1e-3)
    q = rng.uniform(2, 18, (500, 2))
    assert np.max(np.abs(surf(q) - f(q))) < 0.05  # m


def test_mesh_drops_long_edges_and_isolated_points(rng):
    pts = np.c_[rng.uniform(0, 10, (2000, 2)), np.zeros(2000)]
    pts = np.r_[pts, [[30.0, 30.0, 0.0]]]  # isolated
    mesh = fit_ground_mesh(pts, SurfaceParams(grid=0.5, max_edge=1.5, isolated_dist=2.0))
    tri = mesh.vertices[mesh.faces]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
    assert len(mesh) > 500 and edges.max() <= 1.5
    assert mesh.vertices[np.unique(mesh.faces)][:, 0].max() < 11
    assert np.abs(mesh.vertices[:, 2]).max() < 0.01
