"""A candidate whose fit fails is named with its reason and left out; the diagnosis goes on without it.

On Intel, one failed fit (a gradient that was not finite) threw away a whole-catalog run after 417 s.
"""

import json

import drjit as dr
import pytest

from mi_lidar.core.effects.base import EFFECTS, Effect
from mi_lidar.core.params import ParamSpec

from .helpers import diagnose_hidden_bias


class RootBias(Effect):
    """A user's effect with a bug: a range bias of ``sqrt(b)``, whose gradient is infinite at its start ``b = 0``."""

    name = "root_bias"
    specs = {"b": ParamSpec(0.0, "m^2", "square of the bias", lower=0.0, upper=1.0, fit_scale=0.01)}

    def modify_segment(self, seg, rays):
        bias = dr.sqrt(self["b"])
        return seg.with_(mean=seg.mean + bias, lo=seg.lo + bias, hi=seg.hi + bias)


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(EFFECTS, RootBias.name, RootBias)  # removed again after the test


def test_a_candidate_whose_fit_fails_is_named_and_the_run_goes_on(tmp_path, registered):
    result, out = diagnose_hidden_bias(tmp_path, "root_bias", "range_bias")
    assert result.exit_code == 0, result.stdout
    report = json.loads((out / "diagnosis.json").read_text())
    assert report["selected"] == ["range_bias"]  # the other candidate was still tried and found
    [failed] = report["failed"]
    assert failed["candidate"] == "root_bias" and failed["round"] == 1 and failed["stage"] == "screening"
    assert "root_bias.b#0 at 0 (1 of 1 values)" in failed["reason"]
    assert "root_bias" not in {c["name"] for r in report["rounds"] for c in r}  # no ranking row without a fit
    said = " ".join(result.stdout.split())  # rich wraps lines
    assert "The fit of root_bias failed (round 1, screening), so it was left out" in said
    assert "its gradient is not (NaN or infinite) for root_bias.b#0" in said
    page = " ".join((out / "diagnosis.html").read_text().split())
    assert "The fit of root_bias failed (round 1, screening)" in page
