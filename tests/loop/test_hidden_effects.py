"""Hidden-effect tests of the loop: diagnose must name the effect the candidate model lacks.

Each log is simulated from the bundled scenes with one or two effects the candidate model does
not have (per-beam range bias, incidence-angle dropout, range-proportional noise, beam elevation
offsets, mixed pixels, and incidence dropout with outliers). ``diagnose`` fits every candidate on alternate scans
and ranks them on the others; the
hidden effect must come first (both, in either order, for a combination), the augmented model's
held-out NLL must be within 2 % of the true model's, and fitted parameters near the truth.
Candidate lists hold the hidden effect among decoys that could mimic it.
"""

import numpy as np
import pytest

from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.loop import diagnose
from mi_lidar.loop.split import split_rays

from .helpers import hidden_log, room, street


def held_out_nll(scene, model, log) -> float:
    """NLL per ray (nats) of ``model`` on the held-out split diagnose uses."""
    _, test = split_rays(log, 200_000, 200_000)
    problem = Problem.build(scene, LogRays.from_log(log), test)
    return float(-problem.log_likelihood(model).mean())


def check(scene, model, log, true, hidden: list[str], candidates: list[str], rounds: int = 1, steps: int = 100):
    """Run diagnose; assert the ranking and the 2 % NLL criterion; return the diagnosis."""
    d = diagnose(log, scene, model, candidates=candidates, rounds=rounds, steps=steps)
    assert sorted(s.split("(")[0] for s in d.selected) == sorted(hidden), d.summary
    truth = held_out_nll(scene, true, log)
    assert d.nll_after <= truth + 0.02 * abs(truth), (d.nll_after, truth)
    return d


def fitted(d, name: str, key: str) -> np.ndarray:
    """Fitted values of parameter ``key`` of effect ``name`` in the augmented model."""
    return np.asarray(next(e for e in d.model.effects if e.name == name).params[key])


def test_incidence_dropout_is_found():
    scene, model, poses = room(24)
    log, true = hidden_log(scene, model, poses, "incidence_dropout(gamma=2)")
    d = check(scene, model, log, true, ["incidence_dropout"], ["range_dropout", "incidence_dropout", "label_dropout"])
    assert abs(fitted(d, "incidence_dropout", "gamma")[0] - 2.0) < 0.25
    assert d.evidence[0]["groups"][0]["breakdown"] == "incidence"


def test_nothing_hidden_nothing_significant():
    """Negative control: a log from the model itself gives no significant candidate."""
    scene, model, poses = room(24)
    log, _ = hidden_log(scene, model, poses, "")
    d = diagnose(log, scene, model, candidates=["incidence_dropout", "range_noise", "outliers"], rounds=1, steps=80)
    assert d.selected == []
    assert not any(c.significant for c in d.rounds[0])


@pytest.mark.slow
def test_range_proportional_noise_is_found():
    scene, model, poses = room(24)
    log, true = hidden_log(scene, model, poses, "range_noise(law=proportional, sigma0=0, k=0.01)")
    d = check(scene, model, log, true, ["range_noise"], ["range_noise", "quantization", "outliers"])
    assert d.selected[0] == "range_noise(law=proportional)"
    assert abs(fitted(d, "range_noise", "k")[0] - 0.01) < 0.002


@pytest.mark.slow
def test_per_beam_range_bias_is_found():
    scene, model, poses = street(2)
    bias = np.random.default_rng(3).uniform(-0.05, 0.05, 16)
    log, true = hidden_log(scene, model, poses, f"range_bias(bias=[{' '.join(f'{b:.4f}' for b in bias)}])")
    d = check(scene, model, log, true, ["range_bias"], ["range_bias", "range_scale", "range_noise"])
    assert np.max(np.abs(fitted(d, "range_bias", "bias") - bias)) < 0.005


@pytest.mark.slow
def test_beam_elevation_offsets_are_found():
    scene, model, poses = street(2)
    elevation = np.random.default_rng(4).uniform(-0.004, 0.004, 16)
    log, true = hidden_log(scene, model, poses, f"beam_offsets(elevation=[{' '.join(f'{e:.5f}' for e in elevation)}])")
    d = check(scene, model, log, true, ["beam_offsets"], ["beam_offsets", "range_bias", "range_noise"])
    assert np.median(np.abs(fitted(d, "beam_offsets", "elevation") - elevation)) < 0.001


@pytest.mark.slow
def test_mixed_pixels_are_found():
    """Beam divergence of 4 mrad mixes foreground and background ranges at every edge."""
    scene, model, poses = street(2)
    log, true = hidden_log(scene, model, poses, "mixed_pixels(divergence=0.004)")
    d = check(scene, model, log, true, ["mixed_pixels"], ["mixed_pixels", "range_noise", "outliers", "beam_offsets"])
    assert abs(fitted(d, "mixed_pixels", "divergence")[0] - 0.004) < 0.0005


@pytest.mark.slow
def test_combination_of_two_is_found():
    scene, model, poses = room(30)
    log, true = hidden_log(
        scene, model, poses, "incidence_dropout(gamma=2), outliers(p_near=0.05, near_scale=1, uniform_max=30)"
    )
    d = check(
        scene,
        model,
        log,
        true,
        ["incidence_dropout", "outliers"],
        ["incidence_dropout", "outliers", "range_dropout", "range_noise"],
        rounds=2,
    )
    assert sorted(c.name.split("(")[0] for c in d.rounds[0][:1] + d.rounds[1][:1]) == ["incidence_dropout", "outliers"]
    assert abs(fitted(d, "incidence_dropout", "gamma")[0] - 2.0) < 0.25
    assert abs(fitted(d, "outliers", "p_near")[0] - 0.05) < 0.01
