"""Derivative-free tuning of the non-differentiable fitting parameters (thesis 4.4.1).

Tuned (the parameters table 4.1 selects by optimization): ``phi_thresh``, log10 clusters per
point, ellipsoid extent (sigmas), maximum triangle side (m) and maximum residual for hit (m). Objective: mean packet
error + 2 (1 - F1) of the model fitted to the even scans of a
short slice and simulated at its odd scans. Optimizer: scipy Nelder-Mead with a budget of
``max_evals`` fits.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from mi_lidar.core.log import Log
from mi_lidar.hybrid.evaluate import objective, observation_metrics
from mi_lidar.hybrid.fit import FitParams, fit_model, world_rays
from mi_lidar.hybrid.simulation import simulate_log


@dataclass
class TuneResult:
    """Best parameters, objective before and after, and every evaluation (x, objective)."""

    params: FitParams
    initial: float
    best: float
    history: list


def apply_vector(base: FitParams, x: np.ndarray) -> FitParams:
    """Copy of ``base`` with (phi_thresh, log10 clusters_per_point, extent, max_edge, max_residual) = ``x``."""
    p = copy.deepcopy(base)
    p.ground.phi_thresh = float(np.clip(x[0], 0.005, 0.3))
    p.clusters.clusters_per_point = float(10 ** np.clip(x[1], -3, -0.5))
    p.extent = float(np.clip(x[2], 1.0, 6.0))
    p.surface.max_edge = float(np.clip(x[3], 0.5, 20.0))
    p.max_residual = float(np.clip(x[4], 0.05, 3.0))
    return p


def split_objective(log: Log, params: FitParams, seed: int = 0) -> float:
    """Fit to the even scans of ``log``, simulate the odd scans, return packet error + 2 (1 - F1)."""
    train, test = log.select(slice(0, None, 2)), log.select(slice(1, None, 2))
    model = fit_model(train, params).model
    o, d = world_rays(test)
    sim, _ = simulate_log(model, test, seed)
    real = np.where(test.hit, test.ranges, np.nan)
    return objective(observation_metrics(real, sim, o, d))


def tune_parameters(log: Log, base: FitParams | None = None, max_evals: int = 20, seed: int = 0) -> TuneResult:
    """Tune ``base`` on ``log`` (a short slice) with Nelder-Mead; see the module docstring."""
    base = base or FitParams()
    x0 = np.array(
        [
            base.ground.phi_thresh,
            np.log10(base.clusters.clusters_per_point),
            base.extent,
            base.surface.max_edge,
            base.max_residual,
        ]
    )
    history = []

    def f(x):
        value = split_objective(log, apply_vector(base, x), seed)
        history.append((x.tolist(), value))
        return value

    simplex = x0 + np.vstack([np.zeros(5), np.diag([0.03, 0.3, 1.0, 2.0, 0.5])])
    res = minimize(f, x0, method="Nelder-Mead", options={"maxfev": max_evals, "initial_simplex": simplex})
    return TuneResult(apply_vector(base, res.x), history[0][1], float(res.fun), history)
