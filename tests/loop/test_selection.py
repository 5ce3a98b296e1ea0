"""The selection rules of diagnose: ranking, Occam, realism warnings, candidate names (on made-up held-out scores);
shrinking per-beam values without evidence (on a simulated room log)."""

import dataclasses
import json

import numpy as np
import pytest
from scipy import stats

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.loop.catalog import candidate, candidate_names, fans_out
from mi_lidar.loop.realism import realism_warning
from mi_lidar.loop.selection import P_VALUE, Candidate, held_out_test, rank, shrink_without_evidence
from mi_lidar.scene.simulation import simulate
from tests.loop.helpers import room

N = 20_000
RNG = np.random.default_rng(0)
BEFORE = RNG.normal(-2.0, 1.0, N)


def made_up(name: str, k: int, gain: float, noise: float = 0.05, seed: int = 1) -> Candidate:
    """A candidate whose held-out per-ray log-likelihood is BEFORE + gain + its own noise (seeded)."""
    ll = BEFORE + gain + np.random.default_rng(seed).normal(0.0, noise, N)
    g, p = held_out_test(ll, BEFORE)
    return Candidate(name, k, 0.0, g, 0.0, 0.0, p, 0.0, True, {}, test_ll=ll)


def test_the_best_gain_leads_when_it_beats_the_simpler_ones():
    ranked = rank([made_up("simple", 1, 0.10, seed=1), made_up("rich", 5, 0.30, seed=2)])
    assert [c.name for c in ranked] == ["rich", "simple"]


def test_a_simpler_candidate_leads_when_the_best_does_not_beat_it():
    """A per-label dropout with every label alike gains what a random dropout gains, by chance a hair more."""
    ranked = rank([made_up("label_dropout", 5, 0.1002, seed=3), made_up("random_dropout", 1, 0.1000, seed=4)])
    assert [c.name for c in ranked] == ["random_dropout", "label_dropout"]


def metrics(**changes) -> dict:
    base = dict(
        histogram_l1=0.03,
        hit_rate_measured=0.8,
        hit_rate_simulated=0.8,
        range_error_median=0.02,
        range_error_p90=0.06,
    )
    return base | changes


@pytest.mark.parametrize(
    "after,worse",
    [
        (metrics(), False),
        (metrics(range_error_median=0.04, range_error_p90=0.12, histogram_l1=0.02), False),  # a noise law added
        (metrics(histogram_l1=0.06), True),
        (metrics(hit_rate_simulated=0.75), True),
        (metrics(range_error_median=0.43, range_error_p90=0.9, histogram_l1=0.035), True),  # outlier mass
    ],
)
def test_realism_warning_only_when_samples_are_clearly_worse(after, worse):
    text = realism_warning("+ effect", metrics(), after)
    assert bool(text) == worse, text
    if worse:
        assert text.startswith("+ effect lowers the held-out NLL but its samples look less like the sensor")


def test_candidate_names_keep_one_footprint_effect_and_name_both_catalogs_in_errors():
    from mi_lidar.core.effects import make_effect

    assert fans_out("mixed_pixels") and fans_out("multiple_returns") and not fans_out("range_bias")
    names = candidate_names([make_effect("mixed_pixels")])
    assert "multiple_returns" not in names and "mixed_pixels" not in names and "range_bias" in names
    assert candidate_names([], ["np_reg", "range_bias"]) == ["np_reg", "range_bias"]
    assert "np_reg" not in candidate_names([], None, densities=False)
    with pytest.raises(ParameterError, match="np_reg"):
        candidate_names([], ["no_such_effect"])


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        (["np-reg", "p_reg"], [("np_reg", {}), ("p_reg", {})]),
        (["range-bias"], [("range_bias", {})]),
        (["incidence_dropout(law=cos)"], [("incidence_dropout", {"law": "cos"})]),  # as the ranking prints it
        (["range_bias(bias=0.05)"], [("range_bias", {"bias": 0.05})]),  # a value: where the fit starts
        (["incidence_dropout"], [("incidence_dropout", {"law": law}) for law in ("cos", "logistic")]),
    ],
)
def test_a_candidate_is_named_either_way_or_as_diagnose_prints_it(given, expected):
    from mi_lidar.loop.catalog import candidate_settings

    assert candidate_settings([], given) == expected


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ("incidence_dropout(law=tan)", r"law='tan'; choose one of \['cos', 'logistic'\]"),
        ("incidence_dropout(slope=2)", r"unknown parameter\(s\) \['slope'\]; allowed: \[.*'law'"),
        ("np-reg(h=2)", "a learned density takes no options here; write np_reg"),
        ("no-such-effect", "or a learned density: np_reg, p_reg"),
    ],
)
def test_a_wrong_option_of_a_candidate_names_the_allowed_ones(given, message):
    from mi_lidar.loop.catalog import candidate_settings

    with pytest.raises(ParameterError, match=message):
        candidate_settings([], [given])


def test_per_beam_values_without_evidence_are_shrunk_from_two_scores_not_one_per_beam():
    """A hidden 5 cm bias on beams 0-9 (20 rays each) keeps its values; 2 mm on the other 350 beams (about 0.4
    nats over a beam's rays, below the critical 5.4) goes back to 0. Every beam is judged from the rays scored
    twice (the values, then the defaults, summed beam by beam), where the rule set back one beam at a time used
    to score them once per beam (361 times). Fails on the parent: 361 scores."""
    scene, model, poses = room(20)
    bias = candidate("range_bias", 360, 1, bias=np.where(np.arange(360) < 10, 0.05, 0.0).tolist())
    log = simulate(scene, poses=poses, model=dataclasses.replace(model, effects=[bias]), seed=3)
    fitted = candidate("range_bias", 360, 1, bias=np.where(np.arange(360) < 10, 0.05, 0.002).tolist())
    problem = Problem.build(scene, LogRays.from_log(log, scene=scene))
    scored, score = [], problem.log_likelihood
    problem.log_likelihood = lambda m: scored.append(m) or score(m)
    shrink_without_evidence(dataclasses.replace(model, effects=[fitted]), [fitted], problem)
    values = np.asarray(fitted.params["bias"])
    assert np.allclose(values[:10], 0.05) and np.all(values[10:] == 0.0)
    assert len(scored) == 2


def test_a_learned_density_whose_setting_holds_an_option_is_written_as_json():
    """P-Reg's chosen setting holds its escape law by name: the diagnosis JSON once failed on it ("could not convert
    string to float: 'gaussian'") after the whole diagnosis had run; numbers are rounded, the option kept."""
    c = dataclasses.replace(
        made_up("p_reg", 3, 0.1),
        parameters={"p_reg.bandwidths": [0.5, np.float64(12.3456789), "gaussian"], "range_bias.bias": np.array([0.01])},
    )
    row = json.loads(json.dumps(c.row()))
    assert row["parameters"] == {"p_reg.bandwidths": [0.5, 12.345679, "gaussian"], "range_bias.bias": [0.01]}


def test_a_bias_on_every_beam_keeps_the_values_within_their_noise_of_0():
    """A bias on all 360 beams (normal, RMS 2 cm) keeps every value, also those whose rays (20 per beam) cannot
    tell from 0 (likelihood ratio below the critical 5.4: at least 100 beams here); on a log without a bias, values
    that are noise (0.5 mm on every beam) all go back to 0. Zeroing the former is what made the 360 fitted biases
    of a planar log 4.95 % off the truth instead of the 3.90 % of a weighted least-squares fit (sweep
    bias5cm+noise0.01). Fails on the parent: 138 of the 360 values set to 0."""
    scene, model, poses = room(20)
    truth = np.random.default_rng(7).normal(0.0, 0.02, 360)
    for hidden, given in ((truth, truth), (np.zeros(360), np.full(360, 0.0005))):
        bias = candidate("range_bias", 360, 1, bias=hidden.tolist())
        log = simulate(scene, poses=poses, model=dataclasses.replace(model, effects=[bias]), seed=3)
        problem = Problem.build(scene, LogRays.from_log(log, scene=scene))
        fitted = candidate("range_bias", 360, 1, bias=given.tolist())
        full = problem.log_likelihood_by_beam(dataclasses.replace(model, effects=[fitted]), 360)
        weak = full - problem.log_likelihood_by_beam(model, 360) < 0.5 * stats.chi2.isf(P_VALUE, 1)
        shrink_without_evidence(dataclasses.replace(model, effects=[fitted]), [fitted], problem)
        values = np.asarray(fitted.params["bias"])
        if hidden is truth:
            assert weak.sum() >= 100 and np.allclose(values, truth.astype(np.float32))
        else:
            assert weak.all() and np.all(values == 0.0)
