"""3D hidden-effect logs of an independent numpy street (:mod:`tests.hidden.street`): diagnose over the catalog.

Each log (12 sweeps x 16 beams x 900 firings, 172,800 rays) hides one catalog effect, two, none, or
one outside the catalog (a range bias drifting with time). Diagnose must name the hidden effect
first, select nothing else and fit it within 5 % of the truth (2 % for scale, bias and noise); the
null log must have no significant row and no residual structure; the drift must be flagged with the
dimension it varies along (time). Per-beam values are compared by RMS error over RMS truth. All
cases are slow (``make test-all``); ``docs/loop_results.md`` holds their table.
"""

from __future__ import annotations

import numpy as np
import pytest

from .cases import relative_error, run_case
from .street import Hidden, scene_xml, street_log

BIAS = np.random.default_rng(3).uniform(-0.05, 0.05, 16)
ELEVATION = np.random.default_rng(4).uniform(-0.003, 0.003, 16)
# case: (hidden, selected effects, {fitted parameter: (truth, tolerance)})
CASES = {
    "null": (Hidden(), [], {}),
    "range_scale": (Hidden(scale=1.01), ["range_scale"], {"range_scale.scale": (1.01, 0.02)}),
    "range_bias": (Hidden(bias=BIAS), ["range_bias"], {"range_bias.bias": (BIAS, 0.02)}),
    "range_noise": (Hidden(noise_k=0.005), ["range_noise"], {"range_noise.k": (0.005, 0.02)}),
    "incidence_dropout": (
        Hidden(logistic=(60.0, 4.0)),
        ["incidence_dropout"],
        {"incidence_dropout.angle50": (60.0, 0.05), "incidence_dropout.width": (4.0, 0.05)},
    ),
    "label_dropout": (
        Hidden(label_drop={4: 0.4}),
        ["label_dropout"],
        {"label_dropout.drop": ([0, 0, 0, 0, 0.4], 0.05)},
    ),
    "range_dropout": (
        Hidden(range_dropout=(0.3, 2.0)),
        ["range_dropout"],
        {"range_dropout.rate": (0.3, 0.05), "range_dropout.power": (2.0, 0.05)},
    ),
    "random_dropout": (Hidden(random_drop=0.1), ["random_dropout"], {"random_dropout.p_drop": (0.1, 0.05)}),
    "beam_offsets": (Hidden(elevation=ELEVATION), ["beam_offsets"], {"beam_offsets.elevation": (ELEVATION, 0.05)}),
    "extrinsics": (
        Hidden(mount=(0.0, np.radians(0.8), 0.0, 0.0, 0.0, 0.05)),
        ["extrinsics"],
        {"extrinsics.ry": (np.radians(0.8), 0.05), "extrinsics.tz": (0.05, 0.05)},
    ),
    "motion_distortion": (
        Hidden(velocity=(2.0, 0.0, 0.0)),
        ["motion_distortion"],
        {"motion_distortion.vx": (2.0, 0.05)},
    ),
    "mixed_pixels": (
        Hidden(mixed=(0.004, 0.6)),
        ["mixed_pixels"],
        {"mixed_pixels.divergence": (0.004, 0.05), "mixed_pixels.share": (0.6, 0.05)},
    ),
    "outliers": (
        Hidden(near=(0.05, 1.0)),
        ["outliers"],
        {"outliers.p_near": (0.05, 0.05), "outliers.near_scale": (1.0, 0.05)},
    ),
    "quantization": (Hidden(step=0.05), ["quantization"], {"quantization.step": (0.05, 0.05)}),
    "combination": (
        Hidden(bias=BIAS, label_drop={4: 0.4}),
        ["label_dropout", "range_bias"],
        {"range_bias.bias": (BIAS, 0.02), "label_dropout.drop": ([0, 0, 0, 0, 0.4], 0.05)},
    ),
}


def size_error(fitted, truth) -> float:
    """Relative error of a fitted size: per value for scalars, RMS error over RMS truth for arrays."""
    fitted, truth = np.asarray(fitted, float), np.asarray(truth, float)
    if truth.size == 1:
        if truth.item() == 1.01:  # a scale: its departure from 1 is the size
            return relative_error(fitted - 1.0, truth - 1.0)
        return relative_error(fitted, truth)
    return float(np.sqrt(np.mean((fitted - truth) ** 2) / np.mean(truth**2)))


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_catalog_effect(case, tmp_path):
    hidden, names, sizes = CASES[case]
    outcome = run_case(street_log(hidden), scene_xml(), tmp_path)
    if not names:
        assert outcome.selected == [] and outcome.significant_rows == [], outcome.summary
        assert outcome.flagged == [], outcome.summary
        return
    assert outcome.first.split("(")[0] in names, outcome.summary
    assert sorted(outcome.selected) == names, outcome.summary
    for key, (truth, tolerance) in sizes.items():
        assert size_error(outcome.parameters[key], truth) < tolerance, (key, outcome.parameters[key], truth)


@pytest.mark.slow
def test_drift_outside_the_catalog_is_flagged_with_time(tmp_path):
    """A range bias growing 3 cm/s: no catalog effect explains it; the residual test names time."""
    outcome = run_case(street_log(Hidden(drift=0.03)), scene_xml(), tmp_path, out=tmp_path / "report")
    assert "time" in outcome.flagged, outcome.summary
    assert "varies with time" in outcome.summary
    assert (tmp_path / "report" / "residual_structure.png").is_file()
