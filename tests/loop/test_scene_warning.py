"""compare, fit-sensor, diagnose and calibrate warn when few of a log's returns lie on the scene's surfaces."""

import dataclasses

import numpy as np
import pytest
from typer.testing import CliRunner

import mi_lidar
from mi_lidar.cli import app
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.scene.loading import scene_sensor_model
from mi_lidar.scene.sensor_check import SURFACE_TOLERANCE, scene_warnings

from ..conftest import SCENES

ROOM = SCENES / "indoor_planar.xml"


@pytest.fixture(scope="module")
def room():
    scene = mi_lidar.load_scene(ROOM)
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = [0.0, 0.5, 1.0, -0.5]
    return scene, mi_lidar.simulate(scene, poses=poses, seed=1)


def moved(log, dx: float):
    """The same scans, their poses moved ``dx`` m along x (the scene no longer where the log saw it)."""
    poses = log.poses.copy()
    poses[:, 0, 3] += dx
    return dataclasses.replace(log, poses=poses)


def share_on_surface(scene, log) -> tuple[float, np.ndarray, np.ndarray]:
    problem = Problem.build(scene, LogRays.from_log(log))
    near = problem.near_surface(scene_sensor_model(scene)[0], SURFACE_TOLERANCE)
    hit = LogRays.from_log(log).hit
    return near[hit].mean(), near, hit


def test_a_log_in_its_own_scene_lies_on_its_surfaces(room):
    scene, log = room
    share, near, hit = share_on_surface(scene, log)
    assert share > 0.99 and not near[~hit].any()
    assert scene_warnings(near, hit) == []


def test_a_log_whose_poses_are_off_is_warned_about(room):
    """Poses 30 m off put the sensor outside the room: its walls are 25-35 m along the beams, not 1-5 m.

    The check catches such gross mismatches, not small offsets: moved 2 m, 37 % of the returns still lie
    near the first wall along their beam. Walls behind it do not count: with them the figure is 49 %."""
    scene, log = room
    share, near, hit = share_on_surface(scene, moved(log, 30.0))
    assert share < 0.25, share
    (warning,) = scene_warnings(near, hit)
    assert f"only {share:.1%} of {hit.sum():,} measured returns" in warning and "poses" in warning


@pytest.mark.parametrize("verb", ["compare", "fit-sensor", "diagnose", "calibrate"])
def test_the_verbs_print_the_warning(tmp_path, room, verb):
    scene, log = room
    runner = CliRunner()
    for dx, warned in ((0.0, False), (30.0, True)):
        path = moved(log, dx).save(tmp_path / f"log{dx}.npz")
        out = tmp_path / (f"m{dx}.npz" if verb == "fit-sensor" else f"c{dx}")
        extra = {
            "fit-sensor": ["--model", "physics", "--steps", "20"],
            "diagnose": ["--candidate", "range_scale"],
            "calibrate": ["--params", "sensor.range_bias", "--steps", "5"],
        }
        extra = extra.get(verb, [])
        run = runner.invoke(app, [verb, str(path), str(ROOM), "--out", str(out), *extra])
        text = " ".join(run.output.split())
        assert run.exit_code == 0, text
        assert ("warning: only" in text.lower()) == warned, text
        if verb in ("compare", "calibrate"):
            report = (out / ("report.md" if verb == "compare" else "report.html")).read_text()
            assert ("Warning:</b> only" in report or "**Warning:** only" in report) == warned


def test_a_return_behind_an_opaque_wall_is_not_on_a_surface(room):
    """Elements behind the first opaque one along a beam do not count: the beam cannot reach them."""
    scene, log = room
    model = scene_sensor_model(scene)[0]
    rays = LogRays.from_log(log)
    traced = Problem.build(scene, rays)
    traced.trace(model)
    rounds = traced.chunks[0].rounds.rounds
    first = np.full(rays.n, np.nan)
    first[np.asarray(rounds[0].ray)] = np.asarray(rounds[0].nominal)
    behind = np.full(rays.n, np.nan)  # the first element more than 1 m behind the first one (another wall)
    for entries in rounds[1:]:
        ray, nominal = np.asarray(entries.ray), np.asarray(entries.nominal)
        take = np.isnan(behind[ray]) & (nominal > first[ray] + 1.0)
        behind[ray[take]] = nominal[take]
    ray = np.flatnonzero(np.isfinite(behind) & rays.hit)
    assert ray.size > 100, ray.size
    moved_back = dataclasses.replace(rays, measured=rays.measured.copy())
    moved_back.measured[ray] = behind[ray]
    near = Problem.build(scene, moved_back).near_surface(model, SURFACE_TOLERANCE)
    assert not near[ray].any()
    assert near[np.setdiff1d(np.flatnonzero(rays.hit), ray)].all()
