"""What a calibration run produced (:class:`FitResult`) and the warnings that make a fit doubtful.

Written by :meth:`mi_lidar.calibration.fit.Calibration.fit`; read by the report
(:mod:`mi_lidar.calibration.report`) and the ``calibrate`` command's table. Losses are mean
negative scored log-likelihoods per held-out ray, in nats.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from mi_lidar.core.sensor_model import SensorModel


@dataclass
class FitResult:
    """What a calibration run produced.

    Attributes:
        names: fitted parameter names.
        initial, counting, fitted: natural values per name before fitting, after the counting
            estimate (p_hit parameters only) and after fitting (the best held-out values).
        shared: per per-beam parameter fitted first as one shared value, that value (empty: no shared start).
        shared_steps: Adam steps of the shared start (the first rows of ``history``).
        observations: per p_hit parameter, training rays that met each element (hits plus
            pass-throughs of the counting estimate).
        history: rows ``(step, train loss, held-out loss or NaN)``, nats per ray; the shared start's steps first.
        initial_nll, counting_nll, fitted_nll: held-out loss of the initial, counting-estimate
            and fitted models, nats per ray.
        shared_nll: held-out loss after the shared start (``counting_nll`` without one).
        stopped_early: the held-out loss stopped improving before ``steps``.
        steps_run: Adam steps taken.
        table, model: the fitted element table and sensor model.
        samples: ``{"initial", "fitted"}``: the held-out NLL beside the realism of a scan sampled at the
            held-out rays by the initial and the fitted model (:func:`~mi_lidar.core.metrics.metrics_of`).
        warnings: what makes the fit doubtful (e.g. :func:`~mi_lidar.scene.sensor_check.scene_warnings`).
    """

    names: list
    initial: dict
    counting: dict
    fitted: dict
    observations: dict
    history: list
    initial_nll: float
    counting_nll: float
    fitted_nll: float
    stopped_early: bool
    steps_run: int
    table: object
    model: SensorModel
    shared: dict = field(default_factory=dict)
    shared_nll: float = math.nan
    shared_steps: int = 0
    samples: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)


def no_gain_warnings(initial_nll: float, counting_nll: float, fitted_nll: float) -> list[str]:
    """A warning when the fitted model scores the held-out rays worse than the initial one (nats per ray).

    It happens when the initial values already explain the log and the training rays pull the fit off
    them (a log simulated from the scene itself, a parameter the log says little about); the counting
    start can add to it by starting from noisy per-element estimates.
    """
    if not fitted_nll > initial_nll:
        return []
    start = (
        f"; the fit started from the counting estimate, which scored {counting_nll:.5f} (try --no-counting-start)"
        if counting_nll > initial_nll
        else ""
    )
    return [
        f"the fitted values score the held-out rays worse than the initial ones ({fitted_nll:.5f} against "
        f"{initial_nll:.5f} nats/ray): the initial values explain this log at least as well{start}"
    ]
