"""Hidden-effect test with an independent simulator: weak-return dropout written in numpy alone.

The log comes from :mod:`tests.reflective_world` (analytic ray-rectangle intersections, its own
transcription of the detector law); the candidate model has no dropout. ``diagnose`` must name
``reflectivity_dropout`` first among decoys that also thin returns (by range, incidence, label or at
random), its refitted held-out NLL must be within 2 % of the true model's, and the fitted threshold
range within 2 % of the truth (measured: 40.26 m for 40 m, held-out NLL 1.0515 for 1.0514
nats/ray; about 45 s, hence slow).
"""

import dataclasses

import pytest

from mi_lidar.core.effects import parse_effects
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop import diagnose

from ..reflective_world import mitsuba_scene, poses, rectangles, simulate_numpy
from .test_hidden_effects import fitted, held_out_nll

RANGE50, WIDTH = 40.0, 0.4


@pytest.mark.slow
def test_reflectivity_dropout_from_a_numpy_simulator_is_found():
    rects = rectangles()
    scene = mitsuba_scene(rects)
    log = simulate_numpy(rects, poses(10), RANGE50, WIDTH, seed=1)
    model = SensorModel()
    d = diagnose(
        log,
        scene,
        model,
        candidates=["reflectivity_dropout", "range_dropout", "incidence_dropout", "label_dropout"],
        rounds=1,
        steps=100,
    )
    assert d.selected == ["reflectivity_dropout"], d.summary
    assert d.rounds[0][0].name == "reflectivity_dropout"
    true = dataclasses.replace(model, effects=parse_effects(f"reflectivity_dropout(range50={RANGE50}, width={WIDTH})"))
    truth = held_out_nll(scene, true, log)
    assert d.nll_after <= truth + 0.02 * abs(truth), (d.nll_after, truth)
    assert abs(fitted(d, "reflectivity_dropout", "range50")[0] - RANGE50) < 0.02 * RANGE50
    assert abs(fitted(d, "reflectivity_dropout", "width")[0] - WIDTH) < 0.2 * WIDTH
