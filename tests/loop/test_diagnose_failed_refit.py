"""A refit outside the candidate rounds that fails leaves the effects as they were, says so, and the report is written.

Before the rounds, diagnose refits the given model's own effects on the training rays. Once the rounds are over, it
refits the effects found on every training ray (the final joint refit, again after dropping passengers) and, once the
held-out figures are taken, on every ray of the log. Such a refit raising :class:`~mi_lidar.core.errors.FitError` (a
gradient that is not finite on rays the candidate fits never saw) used to end the command with exit code 2 and no
report, after every candidate had been fitted (minutes on a real log).

The failure is injected: every refit goes through ``mi_lidar.loop.catalog.fit_parts``; the stand-in ruins the values of
the refit problem's effects (NaN, as a failed step leaves them) and raises, for the training split's or the whole log's
rays only, so the screening and the round's joint refit still run.
"""

import dataclasses
import json

import mitsuba as mi
import numpy as np
import pytest

from mi_lidar.core.errors import FitError
from mi_lidar.loop import catalog
from mi_lidar.loop.split import Splits

from .helpers import diagnose_hidden_bias

REASON = "fit step 3: the loss is finite (1.5) but its gradient is not (NaN or infinite) for range_bias.bias#0"


@pytest.fixture
def failing_refit(monkeypatch, request):
    """Make the refits on ``request.param`` (``train``: the training split; ``whole``: every ray) fail."""
    marked = set()
    build, whole = Splits.build.__func__, Splits.whole

    def marking_build(cls, *args, **kwargs):
        data = build(cls, *args, **kwargs)
        if request.param == "train":
            marked.add(id(data.train))
        return data

    def marking_whole(self):
        problem = whole(self)
        if request.param == "whole":
            marked.add(id(problem))
        return problem

    fit_parts = catalog.fit_parts

    def failing(model, problem, parts, **kwargs):
        if id(problem) in marked:
            for part in parts:
                for key in part.fitted_names():
                    part.params[key] = mi.Float(np.full(np.size(part.params[key]), np.nan, np.float32))
            raise FitError(REASON)
        return fit_parts(model, problem, parts, **kwargs)

    monkeypatch.setattr(Splits, "build", classmethod(marking_build))
    monkeypatch.setattr(Splits, "whole", marking_whole)
    monkeypatch.setattr(catalog, "fit_parts", failing)
    return request.param


@pytest.mark.parametrize(
    "failing_refit,stage,kept",
    [
        ("train", "final joint refit", "the effects keep the values they had before it"),
        ("whole", "refit on every ray", "the values reported are those fitted on the training rays"),
    ],
    indirect=["failing_refit"],
)
def test_a_failed_refit_after_the_rounds_keeps_the_values_and_the_report(tmp_path, failing_refit, stage, kept):
    result, out = diagnose_hidden_bias(tmp_path, "range_bias")
    assert result.exit_code == 0, result.stdout
    report = json.loads((out / "diagnosis.json").read_text())
    assert report["selected"] == ["range_bias"]
    [failed] = report["failed"]
    assert failed == {"candidate": "range_bias", "round": None, "stage": stage, "reason": REASON, "kept": kept}
    bias = np.asarray(report["parameters"]["range_bias.bias"])  # per beam
    assert np.all(np.isfinite(bias)) and abs(np.median(bias) - 0.05) < 0.005, bias  # the hidden 5 cm, not NaN
    assert abs(report["nll_after"] - report["nll_before"]) > 0.1 and np.isfinite(report["nll_after"])
    sentence = f"The {stage} of range_bias failed, so {kept}"
    assert sentence in " ".join(result.stdout.split())  # rich wraps lines
    assert sentence in " ".join((out / "diagnosis.html").read_text().split())
    scene = (out / "scene.xml").read_text()
    assert "range_bias(bias=[0.0" in scene and "nan" not in scene


def test_a_failed_refit_of_the_given_model_keeps_its_values_and_the_candidates_are_screened(monkeypatch):
    """The given model's effects are refitted on the training rays before the candidates are screened beside them.
    That refit raising :class:`~mi_lidar.core.errors.FitError` ended the whole run before any candidate was tried;
    now the effects keep their values, the verdict names the refit, and the candidates are ranked as before.

    The failure is injected in the first fit of the run (``catalog.fit_parts``), which is that refit."""
    from mi_lidar.core.effects import parse_effects
    from mi_lidar.loop import diagnose

    from .helpers import hidden_log, room

    scene, model, poses = room(6)
    log, _ = hidden_log(scene, model, poses, "range_bias(bias=0.05)")
    given = dataclasses.replace(model, effects=parse_effects("random_dropout(p_drop=0.03)"))
    fitted, fit_parts = [], catalog.fit_parts

    def failing_first(model, problem, parts, **kwargs):
        fitted.append([part.name for part in parts])
        if len(fitted) == 1:
            for part in parts:
                part.params["p_drop"] = mi.Float(np.nan)  # what a failed step leaves
            raise FitError(REASON)
        return fit_parts(model, problem, parts, **kwargs)

    monkeypatch.setattr(catalog, "fit_parts", failing_first)
    result = diagnose(log, scene, given, candidates=["range_bias", "range_scale"], rounds=1)
    assert fitted[0] == ["random_dropout"]  # the failed fit was the given model's refit
    kept = "the effects keep the values they had before it"
    assert result.failed == [
        {
            "candidate": "random_dropout",
            "round": None,
            "stage": "refit before screening",
            "reason": REASON,
            "kept": kept,
        }
    ]
    assert f"The refit before screening of random_dropout failed, so {kept}" in result.summary
    assert {c["name"] for c in result.ranking()} == {"range_bias", "range_scale"}
    assert result.selected == ["range_bias"] and np.isfinite(result.nll_before) and np.isfinite(result.nll_after)
    drop = np.asarray(result.model.effects[0].params["p_drop"])
    assert result.model.effects[0].name == "random_dropout" and np.all(np.isfinite(drop))
