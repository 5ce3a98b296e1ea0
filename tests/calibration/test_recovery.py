"""Recovery: logs simulated from known parameters are fitted back within stated tolerances.

Each test simulates a log with the true parameters, starts the fit from a perturbed model (or
from the effect at identity) and checks the recovered values. Seeds are fixed.
"""

from pathlib import Path

import numpy as np

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import scene_dict

from .scenes import bowl, circle_poses, pattern, shrubs

SCENES = Path(__file__).resolve().parents[2] / "scenes_xml"
P_SHRUBS = [0.25, 0.45, 0.65, 0.35, 0.55, 0.75]
P_GROUND = 0.8


def test_hit_probabilities_recovered_and_autodiff_matches_counting():
    # 8 poses x 16 beams x 800 firings = 102,400 rays.
    truth = {"terrain": bowl(n=9, p_hit=P_GROUND), "shrubs": shrubs(P_SHRUBS)}
    scene = mi_lidar.load_scene(scene_dict(truth))
    model = SensorModel(range_sigma=0.02)
    log = mi_lidar.simulate(scene, pattern(800), poses=circle_poses(8), seed=5, model=model)
    start = {"terrain": bowl(n=9, p_hit=0.5), "shrubs": shrubs([0.5] * 6)}
    fitted_scene = mi_lidar.load_scene(scene_dict(start))
    cal = Calibration(
        fitted_scene,
        log,
        ["elements.*.p_hit"],
        model=model,
        options=FitOptions(steps=60, batch_size=1 << 15, eval_every=5, seed=1),
    )
    result = cal.fit()
    for name, true in (
        ("elements.shrubs.p_hit", np.array(P_SHRUBS)),
        ("elements.terrain.p_hit", np.full(128, P_GROUND)),
    ):
        seen = result.observations[name] >= 1000  # binomial std <= 0.016 at 1000 rays; most elements see far more
        assert seen.sum() >= (6 if "shrubs" in name else 12)
        error = np.abs(result.fitted[name] - true)[seen]
        assert error.max() < 0.02 * 2.5 and np.median(error) < 0.02, f"{name}: errors {np.round(error, 3)}"
        strong = result.observations[name] >= 5000  # std <= 0.007: the 0.02 target of the issue
        assert np.all(np.abs(result.fitted[name] - true)[strong] < 0.02)
    # Autodiff starts from the counting estimate and keeps the best held-out parameters.
    assert result.fitted_nll <= result.counting_nll + 1e-6
    assert result.counting_nll < result.initial_nll - 0.05


def test_range_bias_and_scale_recovered():
    bias = np.random.default_rng(4).uniform(-0.03, 0.03, 16)
    scene = mi_lidar.load_scene(scene_dict({"terrain": bowl(n=17)}))
    text = " ".join(f"{b:.6f}" for b in bias)
    true_model = SensorModel(
        range_sigma=0.01, effects=parse_effects(f"range_scale(scale=1.003), range_bias(bias=[{text}])")
    )
    log = mi_lidar.simulate(scene, pattern(500), poses=circle_poses(4), seed=9, model=true_model)
    cal = Calibration(
        scene,
        log,
        ["sensor.range_bias", "sensor.range_scale"],
        model=SensorModel(range_sigma=0.01),
        options=FitOptions(steps=200, batch_size=1 << 14, eval_every=10, patience=4, seed=3),
    )
    result = cal.fit()
    assert np.abs(result.fitted["sensor.range_bias"] - bias).max() < 0.005
    assert abs(result.fitted["sensor.range_scale"][0] - 1.003) < 5e-4


def test_per_beam_bias_starts_shared_so_sparse_beams_find_it():
    """The README's drive: a VLP-16 2 m up in the off-road scene, a 5 cm bias on every beam. The upward beams
    return from a few tree crowns only, where a bias centimetres off moves returns out of the ellipsoids'
    chords and the loss goes flat: fitted beam by beam from 0 they settle on local optima (two beams at -1.8 and
    -1.4 cm, measured); fitted first as one shared value, every beam starts at the shared 5 cm and stays there."""
    scene = mi_lidar.load_scene(SCENES / "offroad.xml")
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[:, :3, 3] = [[0, 0, 2], [2, 0, 2]]
    true_model = SensorModel(range_sigma=0.02, effects=parse_effects("range_bias(bias=0.05)"))
    log = mi_lidar.simulate(scene, poses=poses, seed=1, model=true_model)
    fits = {}
    for shared in (True, False):
        options = FitOptions(steps=200, seed=0, shared_start=shared)
        fits[shared] = Calibration(scene, log, ["sensor.range_bias"], options=options).fit()
    bias = fits[True].fitted["sensor.range_bias"]
    assert np.abs(bias - 0.05).max() < 0.005, np.round(bias, 4)
    assert abs(fits[True].shared["sensor.range_bias"] - 0.05) < 0.002
    assert fits[True].fitted_nll < fits[False].fitted_nll  # held-out: the local optima are worse
    assert np.abs(fits[False].fitted["sensor.range_bias"] - 0.05).max() > 0.03  # what the shared start prevents
