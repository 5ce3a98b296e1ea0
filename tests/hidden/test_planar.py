"""Planar hidden-effect logs of an independent numpy room (:mod:`tests.hidden.room`): diagnose over the catalog.

Each log (200 scans x 360 beams x 1 firing, 72,000 rays) hides one effect, two, or none. Diagnose
must name the hidden effect first, select nothing else, and refit it within 2 % of the truth; the
null log must have no significant row. Per-beam biases are held to their statistical limit instead
(100 training returns per beam give 1 mm on 3 cm): RMS error within 1.5 times ``sigma / sqrt(n)``.
The combination runs in ``make test`` on a short candidate list; the whole catalog runs in
``make test-all``.
"""

from __future__ import annotations

import numpy as np
import pytest

from .cases import relative_error, run_case
from .room import SIGMA, Hidden, room_log, scene_xml

SCANS = 200
BIAS = np.random.default_rng(5).normal(0.0, 0.03, 360)
CASES = {
    "null": (Hidden(), []),
    "range_scale": (Hidden(scale=1.01), ["range_scale"]),
    "range_bias": (Hidden(bias=BIAS), ["range_bias"]),
    "range_noise": (Hidden(noise_k=0.01), ["range_noise"]),
    "incidence_dropout": (Hidden(logistic=(60.0, 4.0)), ["incidence_dropout"]),
    "combination": (Hidden(scale=1.01, logistic=(60.0, 4.0)), ["incidence_dropout", "range_scale"]),
}


def check_sizes(hidden: Hidden, parameters: dict) -> None:
    """Fitted sizes against the truth (see the module docstring for the tolerances)."""
    if hidden.scale != 1.0:
        assert relative_error(parameters["range_scale.scale"] - 1.0, hidden.scale - 1.0) < 0.02, parameters
    if hidden.bias is not None:
        rms = np.sqrt(np.mean((parameters["range_bias.bias"] - hidden.bias) ** 2))
        assert rms < 1.5 * SIGMA / np.sqrt(SCANS / 2), rms
    if hidden.noise_k:
        assert relative_error(parameters["range_noise.k"], hidden.noise_k) < 0.02, parameters
    if hidden.logistic is not None:
        fitted = (parameters["incidence_dropout.angle50"][0], parameters["incidence_dropout.width"][0])
        assert relative_error(fitted, hidden.logistic) < 0.02, fitted


def test_combination_is_found_on_a_short_list(tmp_path):
    """Scale and logistic incidence dropout, among decoys that could mimic them (make test)."""
    hidden, names = CASES["combination"]
    outcome = run_case(
        room_log(hidden, scans=SCANS),
        scene_xml(),
        tmp_path,
        candidates=["range_scale", "range_bias", "incidence_dropout", "range_dropout", "random_dropout"],
    )
    assert sorted(outcome.selected) == names, outcome.summary
    check_sizes(hidden, outcome.parameters)
    assert outcome.flagged == [], outcome.summary


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_whole_catalog(case, tmp_path):
    hidden, names = CASES[case]
    outcome = run_case(room_log(hidden, scans=SCANS), scene_xml(), tmp_path)
    if not names:
        assert outcome.selected == [] and outcome.significant_rows == [], outcome.summary
        return
    assert outcome.first.split("(")[0] in names, outcome.summary
    assert sorted(outcome.selected) == sorted(names), outcome.summary
    check_sizes(hidden, outcome.parameters)
