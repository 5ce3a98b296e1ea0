"""Every parameter family's autodiff gradient matches central finite differences of the same loss.

The loss is the robust negative log-likelihood (nats) of a few thousand simulated rays with the
segments traced once, so it is a smooth function of the parameters; it is summed in float64.
For each family the gradient ``g`` is projected on two unit directions ``v`` (``g / |g|`` and a
seeded random one) and compared with ``(L(x + h v) - L(x - h v)) / 2h``: the difference must
stay below 3% of ``|g|`` (float32 evaluation noise of the loss is below 0.5% of ``|g|`` at the
chosen steps ``h``). The smoothed ellipsoid loss used while fitting their geometry
(:mod:`mi_lidar.core.smoothing`) is checked the same way, on records traced with its margin.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.effects import RangeNoise, parse_effects
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, pattern, sensor_pose, shrubs

EFFECTS = (
    "range_noise(sigma0=0.01), beam_offsets(elevation=[0.001 -0.002 0.0005], azimuth=[0.001 0 -0.001]), "
    "extrinsics(rz=0.002, tx=0.01), range_scale(scale=1.001), range_bias(bias=[0.003 -0.002])"
)

# name, step h (natural units), starting values (None: the scene's), smoothing (sigmas; 0: exact)
FAMILIES = [
    ("elements.terrain.p_hit", 1e-3, None, 0.0),
    ("elements.shrubs.p_hit", 1e-3, None, 0.0),
    ("elements.terrain.range_sigma", 1e-4, None, 0.0),
    ("classes.1.range_sigma", 1e-4, None, 0.0),
    ("elements.shrubs.centers", 1e-4, None, 0.0),
    ("elements.shrubs.scales", 1e-5, None, 0.0),
    ("terrain.terrain.heights", 1e-3, None, 0.0),
    ("sensor.elevation_offset", 1e-5, None, 0.0),
    ("sensor.azimuth_offset", 1e-5, None, 0.0),
    ("sensor.range_bias", 1e-4, None, 0.0),
    ("sensor.range_scale", 1e-5, None, 0.0),
    ("sensor.extrinsics", 1e-5, None, 0.0),
    ("sensor.extrinsics", 1e-5, np.zeros(6), 0.0),  # at identity, where fitting starts
    ("effects.range_noise.sigma0", 1e-4, None, 0.0),
    ("elements.shrubs.centers", 1e-4, None, 0.05),  # the smoothed training loss of ellipsoid geometry
    ("elements.shrubs.scales", 1e-5, None, 0.05),
]


@pytest.fixture(scope="module")
def problem():
    sets = {"terrain": bowl(p_hit=0.85), "shrubs": shrubs([0.3, 0.5, 0.4, 0.6])}
    sets["terrain"].range_sigma = np.full(len(sets["terrain"].faces), 0.02)
    scene = mi_lidar.load_scene(scene_dict(sets))
    model = SensorModel(range_sigma=0.02, effects=parse_effects(EFFECTS))
    log = mi_lidar.simulate(scene, pattern(300), poses=sensor_pose(0.3, -0.2, 0.4), seed=3, model=model)
    return scene, log, model


def loss_and_gradient(problem, name, start, smoothing=0.0):
    scene, log, model = problem
    cal = Calibration(scene, log, [name], model=model, options=FitOptions(holdout=0.5))
    par = cal.params[name]
    x0 = par.initial if start is None else start
    value = mi.Float(np.asarray(x0, np.float32))
    rays, z, hit, records = cal._records("train", np.arange(len(cal.train)), {name: value}, smoothing)

    def loss(x):
        return cal.log_likelihood({name: x}, rays, z, hit, records, smoothing)

    dr.enable_grad(value)
    ll = loss(value)
    dr.backward(-dr.sum(ll))
    gradient = np.asarray(dr.grad(value), np.float64)
    with dr.suspend_grad():
        f = lambda x: -np.sum(np.asarray(loss(mi.Float(x.astype(np.float32))), np.float64))  # noqa: E731
    return np.asarray(x0, np.float64), gradient, f


@pytest.mark.parametrize(
    "name,h,start,smoothing",
    FAMILIES,
    ids=[f"{n}{'@0' if s is not None else ''}{'~smoothed' if k else ''}" for n, _, s, k in FAMILIES],
)
def test_gradient_matches_finite_differences(problem, name, h, start, smoothing):
    x0, gradient, f = loss_and_gradient(problem, name, start, smoothing)
    assert np.all(np.isfinite(gradient))
    norm = np.linalg.norm(gradient)
    assert norm > 0, f"{name}: zero gradient; the loss does not depend on it"
    random = np.random.default_rng(11).normal(size=x0.shape)
    for v in (gradient / norm, random / np.linalg.norm(random)):
        numeric = (f(x0 + h * v) - f(x0 - h * v)) / (2 * h)
        analytic = float(gradient @ v)
        assert abs(analytic - numeric) <= 0.03 * norm, (
            f"{name}: autodiff {analytic:.6g} vs FD {numeric:.6g} (|g| {norm:.4g})"
        )


def test_range_noise_model_is_unchanged_by_sensor_effects_at_identity(problem):
    # Adding the sensor effects at identity (what selecting sensor.* does) leaves the likelihood unchanged.
    scene, log, _ = problem
    base = SensorModel(range_sigma=0.02, effects=[RangeNoise(sigma0=0.01)])
    a = Calibration(scene, log, ["effects.range_noise.sigma0"], model=base, options=FitOptions(holdout=0.5))
    b = Calibration(scene, log, ["effects.range_noise.sigma0", "sensor.*"], model=base, options=FitOptions(holdout=0.5))
    assert [e.name for e in b.model.effects] == [
        "range_noise",
        "beam_offsets",
        "extrinsics",
        "range_scale",
        "range_bias",
    ]
    values = {n: mi.Float(p.initial.astype(np.float32)) for n, p in b.params.items()}
    la = a.held_out_loss({"effects.range_noise.sigma0": values["effects.range_noise.sigma0"]})
    lb = b.held_out_loss(values)
    assert abs(la - lb) < 1e-4 * abs(la)
