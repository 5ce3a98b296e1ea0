"""Fitting element reflectivities and the sensor's intensity curve to measured intensities, by autodiff.

The loss is the mean negative scored log-likelihood per ray of ranges *and* intensities (the one
pass-through mixture of :mod:`mi_lidar.core.likelihood`, each element's range density times its
intensity density), so every return is explained by the elements that can explain its range. The
fitted numbers are the per-element reflectivities (log scale) and the parameters of the model's
:class:`~mi_lidar.core.intensity.IntensityModel` (per-beam gain, incidence and range exponents,
near-field range, noise), run by the one fitter (:func:`mi_lidar.core.fitting.adam_fit`).

**Shrinkage.** A scene built from a scan has about as many elements as there are rays to fit them
(the Ouster range-image mesh: 11,337 faces for 6,800 calibration returns), so free per-element
reflectivities reproduce every calibration intensity and the noise parameters collapse to their
bounds: the fit then explains nothing new. :func:`fit_intensity` therefore takes a log-normal prior
``ln rho_e ~ N(ln rho0_e, prior_sigma^2)`` about each element's starting reflectivity (the maximum a
posteriori fit), and :func:`calibrate_intensity` chooses ``prior_sigma`` on rays the fit does not
see (0: the starting reflectivities are kept; infinite: no prior), where it also fits the noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import CalibrationError
from mi_lidar.core.fitting import FitVariable, adam_fit
from mi_lidar.core.problem import Problem, make_opaque
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel

REFLECTIVITY_BOUNDS = (1e-3, 100.0)
REFLECTIVITY = "elements.reflectivity"
NOISE = ("noise_floor", "noise_relative", "p_outlier")  # kept while the reflectivities move
PRIOR_SIGMAS = (0.0, 0.1, 0.2, 0.4, 0.8, 1.6, math.inf)  # ln-reflectivity prior widths calibrate_intensity tries


@dataclass
class IntensityFit:
    """Outcome of :func:`fit_intensity`.

    Attributes:
        reflectivity: (E,) fitted per-element reflectivities (the table's order).
        history: the fitted objective at each step: mean scored log-likelihood per ray (nats) plus the
            reflectivity prior's log density over the number of rays.
    """

    reflectivity: np.ndarray
    history: list


def fit_intensity(
    model: SensorModel,
    problem: Problem,
    steps: int = 200,
    lr: float = 0.3,
    prior_sigma: float = math.inf,
    fixed: tuple[str, ...] = (),
) -> IntensityFit:
    """Fit the intensity model of ``model`` (in place) and the elements' reflectivities to ``problem``.

    Args:
        model: the sensor model; its ``intensity`` parameters are replaced by the best values seen.
        problem: the measured rays; built from :class:`~mi_lidar.core.rays.LogRays` that score an
            intensity attribute (``LogRays.from_log(log, intensity=...)``).
        steps: Adam steps.
        lr: learning rate in units of each parameter's step unit.
        prior_sigma: standard deviation (in ``ln rho``) of the prior of each element's reflectivity
            about its starting value: 0 keeps the reflectivities, ``inf`` fits them freely (elements
            no ray meets keep theirs either way).
        fixed: intensity-model parameters to keep (e.g. ``("incidence_exponent",)``).

    Returns:
        The fitted reflectivities (also written into ``problem.table``) and the loss history.

    Raises:
        CalibrationError: the problem's rays carry no intensities, or ``prior_sigma`` is negative.
    """
    if problem.rays.intensity is None:
        raise CalibrationError(
            "fit_intensity: the rays carry no intensities; build them with LogRays.from_log(log, intensity='...')"
        )
    if not prior_sigma >= 0:
        raise CalibrationError(f"fit_intensity: prior_sigma={prior_sigma}; give a width >= 0 (in ln reflectivity)")
    part = model.intensity
    make_opaque(model.parts)
    keys = [key for key in part.fitted_names() if key not in fixed]
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
    free = prior_sigma > 0
    start = np.clip(np.asarray(problem.table.reflectivity, np.float64), *REFLECTIVITY_BOUNDS)
    if free:
        variables.append(FitVariable(REFLECTIVITY, start, *REFLECTIVITY_BOUNDS, scale=0.3, transform="log"))
    log_start = mi.Float(aligned(np.log(start).astype(np.float32)))
    n = max(problem.n, 1)
    problem.trace(model)

    def assign(values: dict) -> None:
        for key in keys:
            part.params[key] = values[f"intensity.{key}"]
        if free:
            problem.table = problem.table.replaced(reflectivity=values[REFLECTIVITY])

    def objective(values, step: int) -> float:
        total = 0.0
        for chunk in problem.chunks:
            assign(values())
            loss = -dr.sum(problem.chunk_log_likelihood(model, chunk)) / n
            dr.backward(loss)
            total += float(loss[0])
        if free and math.isfinite(prior_sigma):
            shift = dr.log(values()[REFLECTIVITY]) - log_start
            penalty = dr.sum(dr.square(shift)) / (2.0 * prior_sigma**2 * n)
            dr.backward(penalty)
            total += float(penalty[0])
        return total

    result = adam_fit(variables, objective, steps, lr=lr)
    assign({name: mi.Float(aligned(value.astype(np.float32))) for name, value in result.values.items()})
    make_opaque([part])
    return IntensityFit(
        reflectivity=np.asarray(problem.table.reflectivity, np.float64),
        history=[-loss for _, loss, _ in result.history],
    )


@dataclass
class IntensityCalibration:
    """Outcome of :func:`calibrate_intensity`.

    Attributes:
        reflectivity: (E,) calibrated per-element reflectivities (the table's order).
        prior_sigma: the chosen prior width (ln reflectivity).
        selection: ``{prior_sigma: NLL}``: mean negative scored log-likelihood per check ray (nats)
            of each tried width.
    """

    reflectivity: np.ndarray
    prior_sigma: float
    selection: dict[float, float]


def calibrate_intensity(
    model: SensorModel,
    scene,
    table: ElementTable,
    rays: LogRays,
    fit_index: np.ndarray,
    check_index: np.ndarray,
    steps: int = 150,
    sigmas: tuple[float, ...] = PRIOR_SIGMAS,
    progress=None,
) -> IntensityCalibration:
    """Calibrate the intensity curve and the elements' reflectivities, the shrinkage and noise chosen on held-out rays.

    Noise and reflectivities are never fitted on the same rays: a noise fitted jointly with free
    per-element values collapses (they absorb the residuals), and a Gaussian whose spread grows with
    its mean biases that mean when the spread is wrong (by 10 % at a relative noise of 0.38 for a
    true 0.1), so the spread has to be right before the reflectivities are.

    1. The whole model (curve: gain, exponents, near range; noise) on ``fit_index``, every element
       keeping its starting reflectivity (``prior_sigma`` 0).
    2. For each width in ``sigmas``: the reflectivities and the curve on ``fit_index`` with that
       prior (the noise kept), then the noise on ``check_index`` (the rest kept), scored there.
    3. At the best width, step 2 once more from its values (the noise the check rays gave).

    The check rays must meet the elements the fit rays meet (e.g. the columns beside them), or the
    widths cannot differ on them.

    Args:
        model: the sensor model; its intensity model is fitted in place.
        scene, table: the scene and its element table (starting reflectivities: the prior's centres).
        rays: the log's rays, with intensities (``LogRays.from_log(log, intensity=...)``).
        fit_index, check_index: disjoint ray indices.
        steps: Adam steps of each fit.
        sigmas: prior widths to try (ln reflectivity; 0 keeps the starting values, ``inf`` is no prior).
        progress: optional ``progress(message)``.

    Returns:
        The calibrated reflectivities, the chosen width and every width's check NLL.
    """
    say = progress or (lambda message: None)
    part = model.intensity
    fit_intensity(model, Problem.build(scene, rays, fit_index, table), steps=steps, prior_sigma=0.0)
    check = Problem.build(scene, rays, check_index, table)

    def fit_at(sigma: float, values: dict) -> tuple:
        """Reflectivities and curve on the fit rays from ``values`` (noise kept), then the noise on the check rays."""
        part.params.update({key: mi.Float(aligned(value)) for key, value in values.items()})
        trial = Problem.build(scene, rays, fit_index, table)
        if sigma > 0:
            fit_intensity(model, trial, steps=steps, prior_sigma=sigma, fixed=NOISE)
        check.table = trial.table
        fit_intensity(model, check, steps=steps, prior_sigma=0.0, fixed=_curve(part))
        return trial.table.reflectivity, _values(part), check.nll(model)

    start, fitted, selection = _values(part), {}, {}
    for sigma in sigmas:
        fitted[sigma] = fit_at(sigma, start)
        selection[sigma] = fitted[sigma][2]
        say(f"reflectivity prior width {sigma:g}: check NLL {selection[sigma]:.4f} nats/ray")
    best = min(selection, key=selection.get)
    reflectivity, values, _ = fit_at(best, fitted[best][1])  # once more, with the noise the check rays gave
    make_opaque([part])
    return IntensityCalibration(
        reflectivity=np.asarray(reflectivity, np.float64), prior_sigma=best, selection=selection
    )


def _values(part) -> dict[str, np.ndarray]:
    """A copy of an intensity model's parameter values (float32 numpy)."""
    return {key: np.asarray(value, np.float32).copy() for key, value in part.params.items()}


def _curve(part) -> tuple[str, ...]:
    """The fitted parameters of an intensity model that are not its noise."""
    return tuple(key for key in part.fitted_names() if key not in NOISE)
