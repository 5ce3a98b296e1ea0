"""Recovery of ellipsoid geometry (centers and scales) with the smoothed training loss.

24 rotated ellipsoids 3-6 m around the sensor over the bowl; a log of 4 poses x 16 beams x 500
firings (32,000 rays) is simulated from the truth, and the fit starts from a seeded perturbation
(centers moved about 3 cm, scales scaled by up to +-20 %). Every fit uses the whole training part
per step (no mini-batch noise) and the default smoothing schedule (0.1 -> 0.01 sigmas). Only
elements that returned >= 100 rays of the log are scored (the others are barely constrained).

Tolerances (measured: see docs/calibration.md):
* scales: median relative error <= 4 % from 9 %, and the held-out NLL ends within 0.08 nats/ray
  of the truth's after starting 0.5 above it;
* centers (scales known): median error < 2.2 cm from 2.8 cm, held-out NLL within 0.06 of the
  truth's (slow: 40 steps).
"""

import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import EllipsoidElements, scene_dict

from .scenes import bowl, bushes, circle_poses, pattern

MODEL = SensorModel(range_sigma=0.02)
SEEN = 100  # returns of the log an element needs to be scored


def perturbed(truth: EllipsoidElements, centers: float, scales: float) -> EllipsoidElements:
    """``truth`` with centers moved by N(0, (centers^2 / 3) I) m and scales times exp(U(-scales, scales)), seeded."""
    rng = np.random.default_rng(1)
    moved = truth.centers + rng.normal(size=truth.centers.shape) * centers / np.sqrt(3)
    return EllipsoidElements(
        centers=moved,
        scales=truth.scales * np.exp(rng.uniform(-scales, scales, truth.scales.shape)),
        quaternions=truth.quaternions,
        p_hit=truth.p_hit,
        label=truth.label,
        extent=truth.extent,
    )


@pytest.fixture(scope="module")
def truth_and_log():
    truth = bushes()
    scene = mi_lidar.load_scene(scene_dict({"terrain": bowl(n=9), "bushes": truth}))
    log = mi_lidar.simulate(scene, pattern(500), poses=circle_poses(4), seed=5, model=MODEL)
    table = ElementTable.from_scene(scene)
    k = table.shape_ids.index("bushes")
    first = sum(table.element_counts[:k])
    element = np.asarray(log.attributes["element_id"]).ravel().astype(np.int64) - first
    ours = log.hit.ravel() & (element >= 0) & (element < len(truth.p_hit))
    returns = np.bincount(element[ours], minlength=len(truth.p_hit))
    return truth, log, returns >= SEEN


def fit(truth, log, start: EllipsoidElements, names: list[str], steps: int):
    cal = Calibration(
        mi_lidar.load_scene(scene_dict({"terrain": bowl(n=9), "bushes": start})),
        log,
        names,
        model=MODEL,
        options=FitOptions(steps=steps, batch_size=1 << 15, eval_every=5, patience=10, seed=1, counting_start=False),
    )
    truth_values = {"elements.bushes.centers": truth.centers.ravel(), "elements.bushes.scales": truth.scales.ravel()}
    truth_nll = cal.held_out_loss({n: mi.Float(truth_values[n].astype(np.float32)) for n in names})
    return cal.fit(), truth_nll


def test_ellipsoid_scales_recovered(truth_and_log):
    truth, log, seen = truth_and_log
    start = perturbed(truth, centers=0.0, scales=0.2)
    result, truth_nll = fit(truth, log, start, ["elements.bushes.scales"], steps=30)
    before = np.abs(start.scales / truth.scales - 1)[seen]
    after = np.abs(result.fitted["elements.bushes.scales"].reshape(-1, 3) / truth.scales - 1)[seen]
    assert seen.sum() >= 18
    assert np.median(after) <= 0.04 and np.median(before) > 0.08, (
        f"median relative errors {np.median(before):.3f} -> {np.median(after):.3f}"
    )
    assert result.initial_nll > truth_nll + 0.3, "the perturbation must matter"
    assert result.fitted_nll < truth_nll + 0.08, (
        f"held-out NLL {result.initial_nll:.3f} -> {result.fitted_nll:.3f} (truth {truth_nll:.3f})"
    )


@pytest.mark.slow
def test_ellipsoid_centers_recovered(truth_and_log):
    truth, log, seen = truth_and_log
    start = perturbed(truth, centers=0.04, scales=0.0)
    result, truth_nll = fit(truth, log, start, ["elements.bushes.centers"], steps=40)
    before = np.linalg.norm(start.centers - truth.centers, axis=1)[seen]
    after = np.linalg.norm(result.fitted["elements.bushes.centers"].reshape(-1, 3) - truth.centers, axis=1)[seen]
    assert np.median(after) < 0.022 and np.median(before) > 0.025, (
        f"median errors (m) {np.median(before):.4f} -> {np.median(after):.4f}"
    )
    assert result.fitted_nll < truth_nll + 0.06, (
        f"held-out NLL {result.initial_nll:.3f} -> {result.fitted_nll:.3f} (truth {truth_nll:.3f})"
    )
