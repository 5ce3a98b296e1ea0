"""Shared small synthetic world, log and fit for the hybrid tests (seconds, not minutes)."""

import numpy as np
import pytest

import mi_lidar  # noqa: F401  (selects the Mitsuba variant)
from mi_lidar.hybrid.fit import FitParams, fit_model
from mi_lidar.hybrid.true_sensor import SensorSpec, path_poses, render_log
from mi_lidar.hybrid.world import WorldSpec, make_world

SMALL_WORLD = WorldSpec(length=36, width=24, object_density=2.0, n_patches=1, n_grass=1)
SMALL_SENSOR = SensorSpec(n_firings=360)


@pytest.fixture(scope="session")
def small_world():
    return make_world(5, SMALL_WORLD)


@pytest.fixture(scope="session")
def small_log(small_world):
    return render_log(small_world, path_poses(small_world, 3.0, SMALL_SENSOR, margin=6.0), SMALL_SENSOR, seed=1)


@pytest.fixture(scope="session")
def small_fit(small_log):
    params = FitParams(block_size=20.0)
    params.ground.phi_thresh = 0.06
    return fit_model(small_log, params)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
