"""Fitting element reflectivities and the sensor's intensity curve to measured intensities, by autodiff.

The loss is the mean negative scored log-likelihood per ray of ranges *and* intensities (the one
pass-through mixture of :mod:`mi_lidar.core.likelihood`, each element's range density times its
intensity density), so every return is explained by the elements that can explain its range. The
fitted numbers are the per-element reflectivities (log scale) and the parameters of the model's
:class:`~mi_lidar.core.intensity.IntensityModel` (per-beam gain, incidence and range exponents,
near-field range, noise), run by the one fitter (:func:`mi_lidar.core.fitting.adam_fit`).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.errors import CalibrationError
from mi_lidar.core.fitting import FitVariable, adam_fit
from mi_lidar.core.problem import Problem, make_opaque
from mi_lidar.core.sensor_model import SensorModel

REFLECTIVITY_BOUNDS = (1e-3, 100.0)
REFLECTIVITY = "elements.reflectivity"


@dataclass
class IntensityFit:
    """Outcome of :func:`fit_intensity`.

    Attributes:
        reflectivity: (E,) fitted per-element reflectivities (the table's order).
        history: mean scored log-likelihood per ray (nats) at each step.
    """

    reflectivity: np.ndarray
    history: list


def fit_intensity(
    model: SensorModel, problem: Problem, steps: int = 200, lr: float = 0.3, reflectivity: bool = True
) -> IntensityFit:
    """Fit the intensity model of ``model`` (in place) and the elements' reflectivities to ``problem``.

    Args:
        model: the sensor model; its ``intensity`` parameters are replaced by the best values seen.
        problem: the measured rays; built from :class:`~mi_lidar.core.rays.LogRays` that score an
            intensity attribute (``LogRays.from_log(log, intensity=...)``).
        steps: Adam steps.
        lr: learning rate in units of each parameter's step unit.
        reflectivity: also fit every element's reflectivity (elements no ray meets keep theirs).

    Returns:
        The fitted reflectivities (also written into ``problem.table``) and the loss history.

    Raises:
        CalibrationError: the problem's rays carry no intensities.
    """
    if problem.rays.intensity is None:
        raise CalibrationError(
            "fit_intensity: the rays carry no intensities; build them with LogRays.from_log(log, intensity='...')"
        )
    part = model.intensity
    make_opaque(model.parts)
    keys = part.fitted_names()
    variables = [
        FitVariable(
            f"intensity.{key}",
            np.asarray(part.params[key], np.float64),
            lower=max(part.specs[key].fit_bound, -1e30),
            upper=min(part.specs[key].upper, 1e30),
            scale=part.fit_scale(key),
        )
        for key in keys
    ]
    if reflectivity:
        variables.append(
            FitVariable(
                REFLECTIVITY,
                np.clip(np.asarray(problem.table.reflectivity, np.float64), *REFLECTIVITY_BOUNDS),
                *REFLECTIVITY_BOUNDS,
                scale=0.3,
                transform="log",
            )
        )
    n = max(problem.n, 1)
    problem.trace(model)

    def assign(values: dict) -> None:
        for key in keys:
            part.params[key] = values[f"intensity.{key}"]
        if reflectivity:
            problem.table = problem.table.replaced(reflectivity=values[REFLECTIVITY])

    def objective(values, step: int) -> float:
        total = 0.0
        for chunk in problem.chunks:
            assign(values())
            loss = -dr.sum(problem.chunk_log_likelihood(model, chunk)) / n
            dr.backward(loss)
            total += float(loss[0])
        return total

    result = adam_fit(variables, objective, steps, lr=lr)
    assign({name: mi.Float(aligned(value.astype(np.float32))) for name, value in result.values.items()})
    make_opaque([part])
    return IntensityFit(
        reflectivity=np.asarray(problem.table.reflectivity, np.float64),
        history=[-loss for _, loss, _ in result.history],
    )
