"""Return distributions of one element: truncated Gaussian sampling and density, ray-restricted ellipsoids."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats

import mi_lidar  # noqa: F401  (selects the variant)
from mi_lidar.core.segment import ELLIPSOID, Segment, log_density, ray_restricted_gaussian, sample_range


def make_segment(n, mean, sigma, lo, hi):
    full = lambda v: dr.full(mi.Float, v, n)  # noqa: E731
    return Segment(
        valid=dr.full(mi.Bool, True, n),
        nominal=full(lo),
        p=full(1.0),
        mean=full(mean),
        sigma=full(sigma),
        lo=full(lo),
        hi=full(hi),
        cos_incidence=full(1.0),
        element=dr.zeros(mi.UInt32, n),
        shape=dr.zeros(mi.UInt32, n),
        label=dr.zeros(mi.UInt32, n),
        kind=dr.full(mi.UInt32, ELLIPSOID, n),
    )


@pytest.mark.parametrize("lo,hi", [(-math.inf, math.inf), (9.0, 10.5), (10.5, 12.0)])
def test_sample_range_matches_truncated_normal(lo, hi):
    n = 200_000
    rng = np.random.default_rng(0)
    seg = make_segment(n, 10.0, 1.0, lo, hi)
    z = np.asarray(sample_range(seg, mi.Float(rng.random(n).astype(np.float32))))
    ref = stats.truncnorm((lo - 10.0), (hi - 10.0), loc=10.0, scale=1.0)
    # Kolmogorov-Smirnov at n = 2e5: the 0.1% critical value is 1.95 / sqrt(n) = 0.0044.
    assert stats.kstest(z, ref.cdf).statistic < 0.0044
    assert z.min() >= lo and z.max() <= hi


def test_log_density_matches_scipy_and_is_minus_inf_outside():
    z = np.array([8.0, 9.5, 10.0, 10.4, 11.0], np.float32)
    seg = make_segment(len(z), 10.0, 0.5, 9.0, 10.5)
    ld = np.asarray(log_density(seg, mi.Float(z)))
    ref = stats.truncnorm(-2.0, 1.0, loc=10.0, scale=0.5).logpdf(z)
    assert np.isneginf(ld[[0, 4]]).all()
    np.testing.assert_allclose(ld[1:4], ref[1:4], rtol=1e-5)


def test_ray_restricted_gaussian_axis_aligned():
    # Ellipsoid at x = 10 with sigma_x = 0.5, extent 3: a ray along +x sees mean 10, sigma 0.5,
    # chord [8.5, 11.5]; a ray offset by 1.5 sigma_y in y sees a chord of half-length 0.5*sqrt(9 - 2.25).
    center = mi.Point3f(10, 0, 0)
    scale = mi.Vector3f(0.5, 0.2, 0.3)
    quat = mi.Vector4f(0, 0, 0, 1)
    mean, sigma, lo, hi = ray_restricted_gaussian(
        center, scale, quat, 3.0, mi.Point3f([0, 0], [0, 0.3], [0, 0]), mi.Vector3f(1, 0, 0)
    )
    np.testing.assert_allclose(np.asarray(mean), [10, 10], atol=1e-5)
    np.testing.assert_allclose(np.broadcast_to(np.asarray(sigma), (2,)), [0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(np.asarray(lo), [8.5, 10 - 0.5 * math.sqrt(9 - 2.25)], atol=1e-5)
    np.testing.assert_allclose(np.asarray(hi), [11.5, 10 + 0.5 * math.sqrt(9 - 2.25)], atol=1e-5)


def test_ray_restricted_gaussian_rotated_matches_direct_formula():
    rng = np.random.default_rng(3)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = 0.7
    q = np.r_[axis * math.sin(angle / 2), math.cos(angle / 2)]
    x, y, z, w = q
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    s = np.array([0.4, 0.9, 0.2])
    cov = rot @ np.diag(s**2) @ rot.T
    mu, o = np.array([5.0, 1.0, 0.5]), np.zeros(3)
    d = np.array([1.0, 0.25, 0.1])
    d /= np.linalg.norm(d)
    prec = np.linalg.inv(cov)
    a = d @ prec @ d
    expect_mean = d @ prec @ (mu - o) / a
    f = lambda v: [float(x) for x in v]  # noqa: E731
    mean, sigma, _, _ = ray_restricted_gaussian(
        mi.Point3f(*f(mu)), mi.Vector3f(*f(s)), mi.Vector4f(*f(q)), 3.0, mi.Point3f(*f(o)), mi.Vector3f(*f(d))
    )
    assert abs(np.asarray(mean)[0] - expect_mean) < 1e-4
    assert abs(np.asarray(sigma)[0] - 1 / math.sqrt(a)) < 1e-5
