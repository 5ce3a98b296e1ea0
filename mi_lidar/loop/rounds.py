"""One round of diagnose's search: every candidate screened, the close race fitted to the end, the winner joined.

A :class:`Round` holds what the round's candidates are judged against: the model as it stands, its held-out
per-ray log-likelihood and its log-likelihood on the fitting rays. :meth:`Round.screen` fits one candidate
beside the model's effects on the fitting subsample and tests it on the held-out rays; :meth:`Round.converged`
fits the candidates in a close race with the leader to the end; :meth:`Round.join` refits the model's effects
with the winner and keeps it only when it still wins held out. :func:`learned_densities` holds the learned
densities, each replacing the given model's density, against the model with the effects found.

Every figure of a candidate row (held-out gain and its paired test, training likelihood ratio, BIC change)
comes from :func:`judged`, whichever of these fitted it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import FitError
from mi_lidar.core.params import Snapshot
from mi_lidar.core.problem import PartsFit, n_parameters
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.catalog import COARSE, SCREEN_TOLERANCE, candidate, fit_density_candidate, refit
from mi_lidar.loop.selection import (
    FAILED,
    JOINED,
    LOST,
    P_VALUE,
    Candidate,
    held_out_test,
    relative_gain,
    significant,
)
from mi_lidar.loop.split import Splits

CLOSE = 0.02  # effects within 2 % of the leader's held-out gain are fitted to the end before the ranking decides
STILL = 1e-9  # nats/ray: a fit to the end is over once its best has not improved by this in a quarter of its steps


def candidate_label(name: str, variant: dict) -> str:
    """``effect`` or ``effect(option=choice)``: a candidate's name in the tables."""
    return name + (f"({', '.join(f'{key}={v}' for key, v in variant.items())})" if variant else "")


def judged(
    test_ll: np.ndarray, reference: np.ndarray, nll: float, train_gain: float, k: int, n_fit: int, threshold: float
) -> dict:
    """The figures of a candidate row (fields of :class:`~mi_lidar.loop.selection.Candidate`).

    Args:
        test_ll: (N,) held-out per-ray log-likelihood with the candidate, nats.
        reference: (N,) the same of the model it is held against, nats.
        nll: held-out NLL per ray the gain is given as a percentage of, nats.
        train_gain: log-likelihood gain on the fitting rays, nats (total).
        k: scalar parameters the candidate adds.
        n_fit: fitting rays.
        threshold: the round's p-value threshold (:func:`~mi_lidar.loop.selection.significant`).
    """
    gain, p = held_out_test(test_ll, reference)
    lr = max(2.0 * train_gain, 0.0)
    return {
        "train_gain": train_gain,
        "test_gain": gain,
        "test_gain_pct": relative_gain(gain, nll),
        "lr": lr,
        "p_value": p,
        "delta_bic": k * math.log(n_fit) - lr,
        "significant": significant(gain, p, threshold),
        "test_ll": test_ll,
    }


@dataclass
class Round:
    """What one round's candidates are judged against.

    Attributes:
        base: the model as it stands (the given one, then with the effects joined so far).
        data: the splits' traced rays.
        steps: Adam steps per fit at most.
        threshold: the round's p-value threshold (Bonferroni over its candidates).
        nll_before: held-out NLL per ray of the given model, nats (gains are given as a percentage of it).
        before_test: (N,) held-out per-ray log-likelihood of ``base``, nats.
        base_fit: log-likelihood of ``base`` on the fitting rays, nats (total).
    """

    base: SensorModel
    data: Splits
    steps: int
    threshold: float
    nll_before: float
    before_test: np.ndarray
    base_fit: float

    def with_effect(self, effect) -> SensorModel:
        """``base`` with ``effect`` added after its effects."""
        return dataclasses.replace(self.base, effects=self.base.effects + [effect])

    def screen(self, name: str, variant: dict) -> Candidate:
        """Fit one candidate on the fitting subsample and test it on the held-out rays.

        Raises:
            FitError: its fit failed (:func:`~mi_lidar.loop.catalog.refit`).
        """
        added = candidate(name, self.data.n_beams, self.data.n_labels, **variant)
        trial = self.with_effect(added)
        fit = refit(trial, self.data.fitting, [added], steps=self.steps, tolerance=SCREEN_TOLERANCE, passes=COARSE)
        k = n_parameters([added])
        return Candidate(
            name=candidate_label(name, variant),
            k=k,
            parameters=fit.parameters,
            history=fit.history,
            effect=added,
            **self._judged(trial, k),
        )

    def converged(self, ranked: list[Candidate], failed: list) -> list[Candidate]:
        """``ranked`` with the effects in a close race refitted to the end (``4 steps`` at most), scored again.

        A screening fit stops once it stops gaining; an effect whose parameters trade off along a narrow
        valley (the constant and proportional parts of a noise law) may stop short of its optimum. So the
        significant effects within :data:`CLOSE` of the leader's held-out gain are fitted to the end before
        the ranking decides. The end is where the best values stop improving at all: a fit whose best has not
        improved (by :data:`STILL`) in ``steps`` steps, a quarter of its budget, is over (on the sweep's planar
        hidden-effect logs every such fit found its best by step 120 of 240 and never improved after it).
        A candidate whose fit to the end fails (:class:`~mi_lidar.core.errors.FitError`) is
        left out, and ``failed`` gets ``(name, stage, reason)``.
        """
        if not ranked or not ranked[0].significant:
            return ranked
        close = [c for c in ranked if c.significant and c.test_gain >= (1.0 - CLOSE) * ranked[0].test_gain]
        if len(close) < 2:
            return ranked
        refitted: dict[int, Candidate | None] = {}
        for c in close:
            trial = self.with_effect(c.effect)
            try:
                fit = refit(trial, self.data.fitting, [c.effect], 4 * self.steps, STILL, window=self.steps)
            except FitError as error:
                failed.append((c.name, "fitted to the end", str(error)))
                refitted[id(c)] = None
                continue
            refitted[id(c)] = self._scored(c, trial, fit)
        return [refitted.get(id(c), c) for c in ranked if refitted.get(id(c), c) is not None]

    def join(self, ranked: list[Candidate], failed: list):
        """The first significant candidate that still wins held out once the model's effects are refitted with it.

        Screening fits a candidate beside the model's effects as they are, so a flexible candidate can win it
        by mending an earlier effect's misfit: after a logistic incidence dropout that absorbed a hidden random
        dropout, a per-label dropout beat the random one by giving the ground (all grazing rays) 0.82. Once the
        winner has won its refit, it and every significant candidate with fewer parameters are refitted with
        the earlier effects to the end (twice the screening's steps, as the final fit; cut short, the earlier
        effects do not adapt), and the first simpler one, in rank order, that the winner does not beat in the
        paired held-out test at :data:`~mi_lidar.loop.selection.P_VALUE` joins instead (the rule of
        :func:`~mi_lidar.loop.selection.rank`, on joint fits). A winner with such simpler rivals is refitted to
        the end at once, and that fit decides whether it wins its refit. Without earlier effects screening is
        already a joint fit, and nothing is refitted again. With earlier effects, a candidate wins its refit by
        beating them refitted to the end without it (:meth:`_refitted_alone`), not as screening left them.
        A candidate whose joint refit fails
        (:class:`~mi_lidar.core.errors.FitError`) does not join: its status says so and ``failed`` gets
        ``(name, stage, reason)``.

        The augmented models share the model's effects, so every joint refit starts from their values as they
        stand, and they end with the values of the refit that joined (as they were when nothing joins): a later
        trial refit used to leave its own values in them, and the next round then judged its candidates against a
        held-out score the model no longer had (every one of them 0.65 nats/ray worse than nothing).

        Returns:
            ``(candidate, augmented model, its held-out per-ray log-likelihood)`` or ``(None, None, None)``.
        """
        if not any(c.significant for c in ranked):
            return None, None, None
        base, data, steps = self.base, self.data, self.steps
        start = Snapshot(base.effects)  # the joint refits share the model's effects: each starts from these values
        before_test = self._refitted_alone(start)

        def joined_with(c: Candidate, thorough: bool = False):
            start.restore()
            augmented = self.with_effect(copy.deepcopy(c.effect))
            try:
                if thorough:  # every step: the earlier effects adapt slowly once the candidate has taken its share
                    refit(augmented, data.fitting, steps=2 * steps)
                else:
                    refit(augmented, data.fitting, steps=steps, tolerance=SCREEN_TOLERANCE)  # earlier effects adapt
            except FitError as error:
                c.status = FAILED
                failed.append((c.name, "joint refit", str(error)))
                return None, None, None
            return augmented, data.test.log_likelihood(augmented), Snapshot(augmented.effects)

        for c in (c for c in ranked if c.significant):
            simpler = [s for s in ranked if s.significant and s.k < c.k and s.status != FAILED] if base.effects else []
            augmented, after_test, fitted = joined_with(c, thorough=bool(simpler))
            if augmented is None:
                continue
            if not significant(*held_out_test(after_test, before_test), self.threshold):
                c.status = LOST
                continue
            for s in simpler:
                model, test, values = joined_with(s, thorough=True)
                if (
                    model is not None
                    and significant(*held_out_test(test, before_test), self.threshold)
                    and (held_out_test(after_test, test)[1] >= P_VALUE)
                ):
                    c, augmented, after_test, fitted = s, model, test, values
                    break
            fitted.restore()  # the effects it shares with the model hold the values of its refit, not of a later trial
            c.status = JOINED
            return c, augmented, after_test
        start.restore()
        return None, None, None

    def _refitted_alone(self, start: Snapshot) -> np.ndarray:
        """The held-out per-ray log-likelihood a candidate must beat to join: the model's, or that of its effects
        refitted to the end without a candidate (twice the screening's steps, from ``start``), whichever is higher.

        A joint refit gives the earlier effects more steps too; when screening left them short of their optimum,
        any candidate gained by those steps alone. A hidden mounting error (street, tests/hidden) was fitted
        first, then a footprint noise joined with it (held-out p 6.5e-83; k 1.9e-5) by taking up the misfit
        of far grazing ground rays that the extrinsics, refitted further, would have removed. The effects
        leave with the values of ``start``.
        """
        if not self.base.effects:
            return self.before_test
        try:
            refit(self.base, self.data.fitting, steps=2 * self.steps)
            alone = self.data.test.log_likelihood(self.base)
        except FitError:
            alone = self.before_test
        start.restore()
        return alone if alone.mean() > self.before_test.mean() else self.before_test

    def _scored(self, c: Candidate, trial: SensorModel, fit: PartsFit) -> Candidate:
        """``c`` scored again with the model ``trial`` after ``fit``."""
        return dataclasses.replace(
            c, parameters=fit.parameters, history=c.history + fit.history, **self._judged(trial, c.k)
        )

    def _judged(self, trial: SensorModel, k: int) -> dict:
        """:func:`judged` of the model ``trial`` (``k`` parameters more than ``base``) against ``base``."""
        train_gain = float(self.data.fitting.log_likelihood(trial).sum()) - self.base_fit
        test_ll = self.data.test.log_likelihood(trial)
        return judged(test_ll, self.before_test, self.nll_before, train_gain, k, self.data.fitting.n, self.threshold)


def learned_densities(names: list[str], given: SensorModel, found: SensorModel, data: Splits, final) -> list:
    """The learned densities, each replacing the given model's density, against the model with the effects found.

    A density is estimated on the estimation rays (its bandwidths chosen on the fitting rays) and
    scored on the held-out rays against ``final`` (the found model's :class:`~mi_lidar.loop.realism.Realism`).
    The best one joins (replacing the effects found) only when it beats that model significantly,
    by :data:`~mi_lidar.loop.selection.MIN_GAIN` at least: a physical effect says why, a learned
    density only what.

    Returns:
        The density rows, best first.
    """
    threshold, rows = P_VALUE / len(names), []
    found_fit = float(data.fitting.log_likelihood(found).sum())
    for name in names:
        states = data.states(given)
        density, table = fit_density_candidate(name, given, states, data.fitting, data.n_labels, data.estimation)
        trial = dataclasses.replace(given, density=density)
        test_ll = data.test.log_likelihood(trial)
        train_gain = float(data.fitting.log_likelihood(trial).sum()) - found_fit
        k = int(sum(np.size(v) for v in density.tables().values()))
        rows.append(
            Candidate(
                name=name,
                k=k,
                parameters={f"{name}.bandwidths": list(min(table, key=lambda row: row[-1])[:-1])},
                kind="density",
                effect=density,
                **judged(test_ll, final.ll, float(-final.ll.mean()), train_gain, k, data.fitting.n, threshold),
            )
        )
    rows.sort(key=lambda c: -c.test_gain)
    if rows and rows[0].significant:
        rows[0].status = JOINED
    return rows
