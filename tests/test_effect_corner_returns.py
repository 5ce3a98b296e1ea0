"""corner_returns: at a depth edge of a range-image mesh, sampled returns land on the foreground or the
background (the mesh's samples), not on the face between them; the likelihood scores such returns higher.

The frame of ``tests/loop/test_real_ouster.py``: ground seen from 1.5 m, a wall 4 m away in columns
80-99; the mesh joins every 4th column, and the rays of the odd columns are simulated in it. Where a
ray crosses a jump face (one corner on the wall, one on the ground behind it), the plain mesh returns
the interpolated range between them.
"""

import mitsuba as mi
import numpy as np

import mi_lidar
from mi_lidar.core.effects import make_effect
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.loop.compare import simulate_log_rays
from mi_lidar.loop.real_ouster import column_log, range_image_mesh
from mi_lidar.scene.dicts import AnalyticElements, scene_dict
from tests.loop.test_real_ouster import synthetic_frame

SIGMA = 0.01  # m


def edge_rays():
    """The scene of the mesh columns and the odd-column rays whose neighbouring samples differ by > 1 m."""
    log = synthetic_frame()
    mesh = range_image_mesh(log, np.arange(0, 256, 4))
    scene = mi.load_dict(scene_dict({"map": mesh}))
    test = column_log(log, np.arange(1, 256, 2))
    r = log.ranges[0]
    column = np.arange(1, 256, 2)
    left, right = r[:, column - column % 4], r[:, (column - column % 4 + 4) % 256]
    edge = (np.abs(left - right) > 1.0).ravel()
    return scene, test, edge, np.stack([left.ravel(), right.ravel()], 1)


def sample(share: float):
    scene, test, edge, corners = edge_rays()
    effects = [make_effect("corner_returns", share=share)] if share else []
    model = mi_lidar.SensorModel(range_sigma=SIGMA, max_segments=2, effects=effects)
    rays = LogRays.from_log(test)
    z, hit = simulate_log_rays(scene, Problem.build(scene, rays).table, rays, model, seed=3)
    return z, hit, edge, corners, scene, rays, model


def test_returns_at_depth_edges_come_from_the_samples_not_from_between_them():
    z, hit, edge, corners, *_ = sample(1.0)
    plain, plain_hit, *_ = sample(0.0)
    on_edge = edge & hit & plain_hit
    assert on_edge.sum() > 20
    distance = np.abs(z[on_edge, None] - corners[on_edge]).min(axis=1)
    plain_distance = np.abs(plain[on_edge, None] - corners[on_edge]).min(axis=1)
    assert np.all(distance < 6 * SIGMA)  # every sample on the wall or on the ground behind it
    assert np.median(plain_distance) > 0.3  # the plain mesh returns from the air between them
    # smooth ground: the corners of the same row lie near the plane; a corner of the next row (whose
    # barycentric weight is small for a ray on a row) is chosen rarely
    assert np.quantile(np.abs(z - plain)[~edge & hit & plain_hit], 0.9) < 0.05


def test_the_likelihood_prefers_the_share_that_simulated_the_scan():
    z, hit, edge, _, scene, rays, model = sample(0.8)
    measured = LogRays(
        log=rays.log,
        scan=rays.scan,
        beam=rays.beam,
        column=rays.column,
        time=rays.time,
        measured=z.astype(np.float32),
        hit=hit,
    )
    problem = Problem.build(scene, measured)
    nll = {}
    for share in (0.0, 0.4, 0.8, 1.0):
        candidate = mi_lidar.SensorModel(
            range_sigma=SIGMA, max_segments=2, effects=[make_effect("corner_returns", share=share)] if share else []
        )
        nll[share] = problem.nll(candidate)
    assert nll[0.8] < min(nll[0.0], nll[0.4], nll[1.0])


def test_fitting_corner_returns_on_analytic_shapes_leaves_the_share_and_gains_nothing():
    """A rectangle has no corners: the likelihood does not depend on the share, so the fit keeps its start
    (the whole-catalog diagnosis of a scene of rectangles screens this candidate)."""
    from mi_lidar.core.problem import fit_parts

    wall = AnalyticElements(plugin="rectangle", to_world=np.diag([4.0, 4.0, 1.0, 1.0]), p_hit=1.0, label=0)
    wall.to_world[2, 3] = 5.0
    scene = mi.load_dict(scene_dict({"wall": wall}))
    directions = np.stack([np.zeros(64), np.linspace(-0.2, 0.2, 64), np.ones(64)], 1)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    ranges = (5.0 / directions[:, 2] + 0.01)[None, :, None]
    log = mi_lidar.Log(
        poses=np.eye(4)[None],
        directions=directions[None, :, None, :],
        ranges=ranges,
        hit=np.ones(ranges.shape, bool),
        times=np.zeros(ranges.shape),
    )
    problem = Problem.build(scene, LogRays.from_log(log))
    effect = make_effect("corner_returns", share=0.3)
    model = mi_lidar.SensorModel(range_sigma=SIGMA, effects=[effect])
    before = problem.nll(model)
    fit = fit_parts(model, problem, [effect], steps=20)
    assert float(np.asarray(fit.parameters["corner_returns.share"]).ravel()[0]) == float(np.float32(0.3))
    assert problem.nll(model) == before


def test_the_corner_spread_is_set_not_fitted():
    """A fitted spread made corner returns a catch-all for stray returns (8 cm on the Ouster frame, 0.6 m on the
    VLP-16) that roughened every sampled surface; fitting moves the share only and keeps the spread given."""
    from mi_lidar.core.problem import fit_parts

    log = synthetic_frame()
    columns = np.arange(log.shape[2])
    scene = mi.load_dict(scene_dict({"map": range_image_mesh(log, columns[columns % 4 == 0])}))
    problem = Problem.build(scene, LogRays.from_log(column_log(log, columns[columns % 4 == 2])))
    effect = make_effect("corner_returns", share=0.3, sigma=0.02)
    assert effect.fitted_names() == ["share"]
    fit_parts(mi_lidar.SensorModel(range_sigma=SIGMA, effects=[effect]), problem, [effect], steps=30)
    assert float(np.asarray(effect["share"])[0]) != float(np.float32(0.3))  # the share was fitted
    assert float(np.asarray(effect["sigma"])[0]) == float(np.float32(0.02))
