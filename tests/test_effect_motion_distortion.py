"""motion_distortion: rays leave from the pose at their own time; velocities recovered."""

import numpy as np
import pytest

from .loop.helpers import hidden_log, recover, room


def test_first_ray_unchanged_and_later_rays_move():
    """At dt = 0 ranges agree to 1 mm (noise-free); late in the sweep a 3 m/s motion shows."""
    scene, model, poses = room(2)
    model.range_sigma = 0.0
    moving, _ = hidden_log(scene, model, poses, "motion_distortion(vx=3, period=0.1)")
    still, _ = hidden_log(scene, model, poses, "motion_distortion(vx=0, period=0.1)")
    assert abs(moving.ranges[0, 0, 0] - still.ranges[0, 0, 0]) < 1e-3
    assert np.nanmax(np.abs(moving.ranges[0, 300:, 0] - still.ranges[0, 300:, 0])) > 0.1


@pytest.mark.slow
def test_recovers_planar_velocity():
    """vx = 3 m/s and wz = 1 rad/s come back within 10 % (the other components stay near 0)."""
    scene, model, poses = room(30)
    log, _ = hidden_log(scene, model, poses, "motion_distortion(vx=3, wz=1.0, period=0.1)")
    effect, _ = recover(scene, model, log, "motion_distortion", steps=200, period=0.1)
    assert abs(float(np.asarray(effect["vx"])[0]) - 3.0) < 0.3
    assert abs(float(np.asarray(effect["wz"])[0]) - 1.0) < 0.1


DRIFTING = 3600.0 + np.arange(4) * 0.1037  # s: sweeps an hour into a log, 3.7 ms late each (not multiples of 0.1)


def test_distortion_reads_the_time_since_the_sweep_start():
    """A sweep distorts the same whenever it starts: scans whose start times drift against the period, an
    hour into the log, equal those started at multiples of it (same seed). Before, ``dt = time mod period``
    of the time since the log's start put these sweeps' rays up to 0.1 s off (and float32 times an hour in
    are 0.24 ms coarse): ranges differed by up to 7.3 m, where a ray turned onto another wall."""
    import dataclasses

    from mi_lidar import simulate
    from mi_lidar.core.effects import parse_effects

    scene, model, poses = room(4)
    model.range_sigma = 0.0
    true = dataclasses.replace(model, effects=model.effects + parse_effects("motion_distortion(vx=3, period=0.1)"))
    regular = simulate(scene, poses=poses, model=true, seed=1)
    drifting = simulate(scene, poses=poses, model=true, seed=1, scan_times=DRIFTING)
    np.testing.assert_array_equal(drifting.hit, regular.hit)
    np.testing.assert_allclose(drifting.ranges, regular.ranges, atol=1e-5, equal_nan=True)


def test_log_rays_carry_the_time_since_the_sweep_start():
    """Scored rays get the time since their scan's first ray, exact to 1 us with absolute (epoch) timestamps,
    and the likelihood of a distorted log does not depend on when its sweeps started. Before, the rays'
    times were the log's (relative to its first ray) in float32: 0.3 s off for these sweeps."""
    import dataclasses

    from mi_lidar import simulate
    from mi_lidar.core.effects import parse_effects
    from mi_lidar.core.problem import Problem
    from mi_lidar.core.rays import LogRays

    scene, model, poses = room(4)
    true = dataclasses.replace(model, effects=model.effects + parse_effects("motion_distortion(vx=3, period=0.1)"))
    regular = simulate(scene, poses=poses, model=true, seed=1)
    epoch = dataclasses.replace(regular, times=regular.times + 1.7e9 + (DRIFTING - 3600.0)[:, None, None])
    since_start = regular.times - regular.times[:, :1, :1]
    for log in (regular, epoch):
        rays, _, _ = LogRays.from_log(log, relative_time=False).batch()
        np.testing.assert_allclose(np.asarray(rays.time), since_start.ravel(), atol=1e-6)
    nll = [Problem.build(scene, LogRays.from_log(log)).nll(true) for log in (regular, epoch)]
    assert nll[1] == pytest.approx(nll[0], abs=1e-6)
