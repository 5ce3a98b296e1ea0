"""Finite-difference checks of every differentiable parameter of every catalog effect and density.

For each case of :mod:`tests.core.catalog` and each of its fitted parameters, the autodiff
derivative of the summed scored log-likelihood of a simulated street log (1440 rays) is compared with
a central finite difference (step 0.002 step units; float64 sums of float32 per-ray values) of the same function: the
likelihood on the trace taken at the trial values. For parameters that move rays (beam angles,
extrinsics, motion, footprint) that function follows each surface's traced tangent plane, the
function the fitter differentiates between re-traces; re-tracing at each finite-difference point
would add the jumps of rays that change surface, which no gradient describes. Tolerance: 5 % of the larger
of the two, plus 0.5 nats per step unit of the parameter (the finite difference's own
float32 noise). The number of checked parameters is printed at the end of the run.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_lidar.core.problem import Problem

from .catalog import case_ids, label, make_part, model_with, simulated, street

PARAMETERS = []
for _case in case_ids():
    _part = make_part(_case, 0.0, 16, 8)
    PARAMETERS += [(_case, key) for key in _part.fitted_names()]


@pytest.mark.parametrize("case,key", PARAMETERS, ids=[f"{label(c)}.{k}" for c, k in PARAMETERS])
def test_gradient_matches_finite_difference(case, key, fd_counter):
    scene, model, pattern, _ = street()
    log, rays = simulated(case)
    trial = make_part(case, 0.5, pattern.shape[0], 8)
    trial_model = model_with(model, case, trial)
    problem = Problem.build(scene, rays)
    problem.trace(trial_model)
    value = np.asarray(trial.params[key], np.float64)
    scale = trial.fit_scale(key)
    h = 0.002 * scale  # small: the likelihood of ray-moving parameters curves within a step unit

    def total(x: np.ndarray, grad: bool = False) -> float:
        param = mi.Float(x.astype(np.float32))
        if grad:
            dr.enable_grad(param)
        trial.params[key] = param
        if grad:
            ll = dr.sum(problem.chunk_log_likelihood(trial_model, problem.chunks[0]))
            dr.backward(ll)
            return float(dr.grad(param)[0])
        return float(np.sum(np.asarray(problem.chunk_log_likelihood(trial_model, problem.chunks[0]), np.float64)))

    auto = total(value, grad=True)
    plus, minus = value.copy(), value.copy()
    plus[0] += h
    minus[0] -= h
    numeric = (total(plus) - total(minus)) / (2 * h)
    fd_counter.append(f"{label(case)}.{key}")
    assert abs(auto - numeric) <= 0.05 * max(abs(auto), abs(numeric)) + 0.5 / scale, (auto, numeric)
