import numpy as np

from mi_lidar.hybrid.ellipsoids import ClusterParams, fit_ellipsoids, hierarchical_kmeans
from mi_lidar.hybrid.model import EllipsoidSet


def test_requested_count_and_min_points(rng):
    pts = rng.normal(0, 3, (5000, 3))
    labels = hierarchical_kmeans(pts, 100, min_points=5)
    counts = np.bincount(labels)
    assert len(counts) == 100 and counts.min() >= 5


def test_separated_blobs_are_split_apart(rng):
    a = rng.normal([0, 0, 0], 0.2, (300, 3))
    b = rng.normal([10, 0, 0], 0.2, (300, 3))
    labels = hierarchical_kmeans(np.r_[a, b], 2)
    assert len(set(labels[:300])) == 1 and len(set(labels[300:])) == 1 and labels[0] != labels[-1]


def test_min_points_stops_splitting(rng):
    labels = hierarchical_kmeans(rng.normal(size=(30, 3)), 100, min_points=10)
    assert np.bincount(labels).min() >= 10 and labels.max() + 1 <= 3


def test_ellipsoid_moments_match_cluster(rng):
    cov = np.array([[1.0, 0.3, 0], [0.3, 0.5, 0], [0, 0, 0.1]])
    pts = rng.multivariate_normal([1, 2, 3], cov, 20000)
    ell, member = fit_ellipsoids(pts, ClusterParams(clusters_per_point=1 / 20000))
    assert len(ell) == 1 and np.all(member == 0)
    np.testing.assert_allclose(ell.covs[0], cov, atol=0.03)
    np.testing.assert_allclose(ell.means[0], [1, 2, 3], atol=0.02)


def test_axes_round_trip(rng):
    a = rng.normal(size=(20, 3, 3))
    e = EllipsoidSet(rng.normal(size=(20, 3)), a @ a.transpose(0, 2, 1) + 0.01 * np.eye(3))
    scales, quats = e.axes(min_sigma=1e-6)
    np.testing.assert_allclose(EllipsoidSet.from_axes(e.means, scales, quats).covs, e.covs, atol=1e-9)
