"""Candidates for diagnosis, and how each is fitted: every registered effect, and the learned densities.

**Effects.** An effect's :class:`~mi_lidar.core.params.ParamSpec` declarations carry everything
diagnosis needs: the fitting start (``fit_start``, where the default sits on a boundary with no
gradient), the step unit (``fit_scale``), parameters kept fixed (``fit=False``), and per-beam /
per-label widths. Options listed in the class's ``variant_options`` are tried as separate candidates
(each noise law, each dropout law).

**Learned densities** (:data:`DENSITY_CANDIDATES`: NP-Reg and P-Reg, thesis ch. 3.3-3.4) replace the
model's return density instead of adding to it. They are estimated in closed form from the training
rays that the effects are not fitted on, their bandwidths chosen on the fitting rays
(:func:`fit_density_candidate`), so the held-out rays judge them exactly as they judge an effect.

**Fitting** (:func:`refit`): the one fitter (projected Adam, :func:`~mi_lidar.core.problem.fit_parts`),
then, for the per-beam parameters of effects that move rays (beam elevation and azimuth offsets), a
search beam by beam. Their gradients come from the tangent planes of the surfaces the rays met at the
last trace, so they cannot see a ray that moves onto another surface (a roof line, a car's top, the
ground behind a wall), which is all a beam that only meets vertical walls tells about its elevation.
Each ray belongs to one beam, so the likelihood is a sum of per-beam terms and every beam's value is
searched at once on a grid that narrows around the best value (:func:`search_by_beam`), each point
traced anew.
"""

from __future__ import annotations

import dataclasses

import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.effects.base import EFFECTS, Effect, FootprintEffect
from mi_lidar.core.errors import FitError, ParameterError
from mi_lidar.core.params import Snapshot, catalog_name, parse_calls
from mi_lidar.core.problem import PartsFit, Problem, fit_parts, make_opaque
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.sensor_fit import crediting, fit_density

DENSITY_CANDIDATES = {"np_reg": "np-reg", "p_reg": "p-reg"}  # candidate name: fit-sensor family
# bandwidths screened (fit-sensor tries 12 pairs; P-Reg's local regressions cost 0.6 s of CPU per pair)
DENSITY_OPTIONS = {
    "np_reg": {"h_ranges": (1.0, 4.0), "h_incidences": (5.0, 20.0)},
    "p_reg": {"h_ranges": (1.0, 4.0), "h_incidences": (10.0,)},
}
SCREEN_TOLERANCE = 1e-3  # nats/ray: a screening fit stops once it gains less than this over 10 to 15 steps
# (effect, option, choice): the choice whose likelihood it shares (MultipleReturns scores strongest as first)
SCORED_AS = {("multiple_returns", "mode", "strongest"): "first"}
COARSE = ((6, 1.0), (3, 1 / 3), (3, 1 / 9), (3, 1 / 27))  # (half points, step in fit_scale units) per pass
FINE = ((3, 1 / 9), (3, 1 / 27), (3, 1 / 81))  # around values already fitted


def candidate(name: str, n_beams: int, n_labels: int, **options) -> Effect:
    """Effect ``name`` at its fitting start, widened to the log's beams and labels.

    Args:
        name: catalog name.
        n_beams: beams (rows) of the log.
        n_labels: class labels of the scene.
        **options: option choices (and parameter overrides) of this candidate.
    """
    effect = EFFECTS[name](**options).widen(n_beams, n_labels).at_fit_start()
    for key, value in options.items():
        if key in effect.specs:  # an explicit starting value wins over the spec's fit_start
            effect.params[key] = type(effect.params[key])(value)
    return effect.widen(n_beams, n_labels)


def variants(name: str, given: dict | None = None) -> list[dict]:
    """Option settings to try for effect ``name``: every combination of its ``variant_options``.

    Choices scored with another choice's likelihood are left out (:data:`SCORED_AS`): their row would
    repeat the other's.

    Args:
        name: catalog name.
        given: option choices (and starting values) the user fixed (:func:`parse_candidate`): a fixed
            option is not varied, and every setting carries them.
    """
    given = given or {}
    if name in DENSITY_CANDIDATES:
        return [{}]
    cls = EFFECTS[name]
    settings: list[dict] = [{}]
    for option in cls.variant_options:
        choices = [c for c in cls.options[option] if (name, option, c) not in SCORED_AS]
        choices = [given[option]] if option in given else choices
        settings = [{**s, option: choice} for s in settings for choice in choices]
    return [{**s, **given} for s in settings]


def parse_candidate(text: str) -> tuple[str, dict]:
    """A candidate as the user names it: ``np-reg`` or ``np_reg``, or as diagnose prints it.

    ``incidence_dropout(law=cos)`` is the candidate with that option fixed; a parameter's value, e.g.
    ``range_bias(bias=0.05)``, is where its fit starts.

    Returns:
        ``(catalog name, given options and starting values)``.

    Raises:
        ParameterError: the name is in neither catalog (the message lists both), or an option or value is not one of
            the effect's (the message lists the allowed ones).
    """
    calls = parse_calls(text, lambda name, **values: (catalog_name(name), values), "candidate")
    if len(calls) != 1:
        raise ParameterError(
            f"candidate {text!r}: give one effect or learned density, e.g. 'incidence_dropout(law=cos)'"
        )
    name, given = calls[0]
    if name in DENSITY_CANDIDATES:
        if given:
            raise ParameterError(f"candidate {text!r}: a learned density takes no options here; write {name}")
        return name, given
    try:
        cls = EFFECTS.cls(name)
    except ParameterError as error:
        raise ParameterError(f"{error}; or a learned density: {', '.join(DENSITY_CANDIDATES)}") from None
    cls(**given)  # an unknown option or a bad value: the effect's own message names the allowed ones
    return cls.name, given


def candidate_settings(
    present: list[Effect], include: list[str] | None = None, densities: bool = True
) -> list[tuple[str, dict]]:
    """The ``(name, options)`` of every candidate to screen: :func:`candidate_names`, each with its :func:`variants`.

    Args:
        present: the model's effects.
        include: candidates as the user names them (:func:`parse_candidate`); None: the whole catalog.
        densities: offer the learned densities when ``include`` is None.
    """
    parsed = [parse_candidate(text) for text in include] if include is not None else None
    names = candidate_names(present, None if parsed is None else [n for n, _ in parsed], densities)
    settings = []
    for name, given in parsed or [(n, {}) for n in names]:
        for variant in variants(name, given) if name in names else []:
            if (name, variant) not in settings:
                settings.append((name, variant))
    return settings


def candidate_names(present: list[Effect], include: list[str] | None = None, densities: bool = True) -> list[str]:
    """Registered effects not yet in the model, then the learned densities (``include`` restricts and orders them).

    A model holds one effect that fans beams out (:class:`~mi_lidar.core.effects.base.FootprintEffect`):
    when it has one, the others are left out.

    Args:
        present: the model's effects.
        include: names to try (effects or :data:`DENSITY_CANDIDATES`, either spelling, :func:`catalog_name`);
            None: every effect and, with ``densities``, every learned density.
        densities: offer the learned densities when ``include`` is None.

    Raises:
        ParameterError: a name of ``include`` is in neither catalog (the message lists both).
    """
    have = {e.name for e in present}
    fanned = any(isinstance(e, FootprintEffect) for e in present)  # a model holds one footprint effect
    if include is None:
        names = sorted(EFFECTS) + (list(DENSITY_CANDIDATES) if densities else [])
    else:
        names = [parse_candidate(n)[0] for n in include]
    return [n for n in names if n not in have and not (fanned and fans_out(n))]


def fans_out(name: str) -> bool:
    """True when candidate ``name`` fans beams out into sub-rays (a model holds one such effect)."""
    return name not in DENSITY_CANDIDATES and issubclass(EFFECTS[name], FootprintEffect)


def search_by_beam(model: SensorModel, effect: Effect, key: str, problem: Problem, passes=COARSE) -> None:
    """Search every beam's value of the per-beam parameter ``key`` of ``effect`` at once (in place).

    Each pass tries the current values shifted by ``-half .. half`` steps (the same shift for every
    beam, traced anew) and keeps, beam by beam, the value whose rays score best; the next pass
    narrows around it.

    Args:
        model: the model holding ``effect``.
        effect: a ray-moving effect.
        key: a per-beam parameter of it.
        problem: the rays it is fitted on.
        passes: ``(half, step)`` per pass, the step in units of the parameter's ``fit_scale``.
    """
    spec = effect.specs[key]
    values = np.asarray(effect.params[key], np.float64).copy()

    def score(trial: np.ndarray) -> np.ndarray:
        effect.params[key] = mi.Float(aligned(trial.astype(np.float32)))
        make_opaque([effect])
        return problem.log_likelihood_by_beam(model, values.size)

    best = score(values)
    for half, step in passes:
        centre = values.copy()
        for shift in np.arange(-half, half + 1) * step * effect.fit_scale(key):
            if shift == 0.0:
                continue
            trial = np.clip(centre + shift, spec.fit_bound, spec.upper)
            ll = score(trial)
            better = ll > best
            values[better], best[better] = trial[better], ll[better]
    score(values)


def refit(
    model: SensorModel,
    problem: Problem,
    parts: list | None = None,
    steps: int = 60,
    tolerance: float | None = None,
    passes=FINE,
    window: int | None = None,
) -> PartsFit:
    """Fit ``parts`` of ``model`` (default: every effect) on ``problem``: the one fitter, then :func:`search_by_beam`.

    Args:
        model: the model (changed in place).
        problem: the rays fitted on.
        parts: the effects to fit (default: all of the model's).
        steps: Adam steps.
        tolerance: stop Adam once it gains less than this (nats/ray) over 10 steps, 15 for effects that
            move rays (None: all steps).
        window: the steps ``tolerance`` looks back instead (None: as above).
        passes: grid passes of the beam-by-beam search (:data:`COARSE` from a fitting start,
            :data:`FINE` around fitted values).

    Returns:
        The fit (history and the fitted values after the search).
    """
    parts = model.effects if parts is None else parts
    fit = fit_parts(model, problem, parts, steps=steps, tolerance=tolerance, window=window)
    for part in parts:
        if isinstance(part, Effect) and part.moves_rays:
            for key in part.fitted_names():
                if part.specs[key].per_beam:
                    search_by_beam(model, part, key, problem, passes)
                    fit.parameters[f"{part.name}.{key}"] = np.asarray(part.params[key])
    return fit


def refit_or_keep(model: SensorModel, problem: Problem, steps: int) -> FitError | None:
    """:func:`refit` every effect of ``model`` on ``problem``; when the fit fails, the effects keep the values they had.

    Returns:
        None, or the :class:`~mi_lidar.core.errors.FitError` of the fit that failed (``model`` is then as it was).
    """
    saved = Snapshot(model.effects)
    try:
        refit(model, problem, steps=steps)
    except FitError as error:
        saved.restore()
        return error
    return None


def fit_density_candidate(
    name: str, base: SensorModel, states, fitting: Problem, n_labels: int, estimation: Problem | None = None
):
    """The learned density ``name`` estimated from ``states``, its bandwidths chosen on ``fitting``'s rays.

    Args:
        name: a key of :data:`DENSITY_CANDIDATES`.
        base: the current model (its effects apply on top of the new density).
        states: :class:`~mi_lidar.core.densities.samples.StateSamples` of training rays not in ``fitting``.
        fitting: the rays that choose the bandwidths.
        n_labels: class labels of the scene.
        estimation: the rays of ``states``: in scenes with permeable elements their returns are then
            credited to the elements that produced them (:func:`~mi_lidar.loop.sensor_fit.crediting`).

    Returns:
        ``(density, bandwidth table)``.
    """

    def validation_nll(density) -> float:
        return fitting.nll(dataclasses.replace(base, density=density))

    family = DENSITY_CANDIDATES[name]
    credit = None if estimation is None else crediting(estimation, base)
    options = DENSITY_OPTIONS.get(name, {})
    return fit_density(family, base, states, validation_nll, n_labels, fitting, 0, credit=credit, **options)
