"""Which candidate joins the model: one held-out test for the tables and the verdict alike.

* **held-out significance** (:func:`held_out_test`): the per-ray gains of the held-out
  log-likelihood (candidate minus current model) are tested with a one-sided paired z-test; a
  candidate is *significant* when ``p < P_VALUE / candidates`` (Bonferroni over the round's
  candidates) and its mean gain is at least :data:`MIN_GAIN` (smaller gains on a large log are
  significant but are the leftovers of an imperfect fit of the effects already found, not a new
  physical effect). The training likelihood ratio and BIC change are reported beside it, not used.
* **ranking** (:func:`rank`): by held-out gain, except that a simpler candidate (fewer parameters)
  goes first when the best one does not beat it significantly held out (a per-label dropout with
  every label alike is a random dropout);
* **joining** (:func:`significant`): a candidate joins only when, after every effect of the
  augmented model is refitted together, the augmented model still passes the same test against the
  current one.
* **passengers** (:func:`drop_passengers`): after the final joint refit, an effect that joined only to
  take up what an earlier one had not yet fitted, or to stand in for effects found after it (a noise
  law widened over a range scale and a per-beam bias), is dropped when the model without it is not
  significantly worse held out.
* **shrinkage** (:func:`shrink_without_evidence`): per-beam or per-label values whose likelihood ratio
  against the parameter's default is below the chi-square(1) critical value go back to the default; a
  per-beam value below it stays when the beams' values as a whole make it more likely off its default
  than on it (:func:`default_posterior`): a bias on every beam keeps its small values.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import mitsuba as mi
import numpy as np
from scipy import stats

from mi_lidar.core.arrays import aligned
from mi_lidar.core.problem import Problem, make_opaque
from mi_lidar.core.sensor_model import SensorModel

P_VALUE = 1e-3
MIN_GAIN = 0.01  # nats/ray: the smallest held-out gain that counts as a missing effect
MIN_NLL_FOR_PERCENT = 1.0  # nats/ray: below this a gain relative to the NLL is not meaningful

JOINED = "joined"
LOST = "lost in the joint refit"
DROPPED = "dropped after the final refit"
REPLACED = "replaced by a learned density"
FAILED = "fit failed"


def relative_gain(gain: float, nll: float) -> float:
    """``gain`` as a percentage of ``|nll|`` (NaN when ``|nll| < MIN_NLL_FOR_PERCENT``).

    An NLL per ray is a log-density: its zero depends on the range unit and bin, so a percentage
    of a value near zero says nothing; the absolute gain in nats/ray is the measure then.
    """
    return 100.0 * gain / abs(nll) if abs(nll) >= MIN_NLL_FOR_PERCENT else float("nan")


def held_out_test(after: np.ndarray, before: np.ndarray) -> tuple[float, float]:
    """Mean per-ray gain (nats) of ``after`` over ``before`` and the one-sided p-value of the paired z-test."""
    diff = after - before
    gain = float(diff.mean())
    error = float(diff.std(ddof=1) / math.sqrt(diff.size)) if diff.size > 1 else 0.0
    if error == 0.0:
        return gain, 0.0 if gain > 0 else 1.0
    return gain, float(stats.norm.sf(gain / error))


def significant(gain: float, p_value: float, threshold: float) -> bool:
    """The one rule: ``p_value`` below ``threshold`` and a mean held-out gain of at least :data:`MIN_GAIN`."""
    return bool(p_value < threshold and gain >= MIN_GAIN)


@dataclass
class Candidate:
    """One fitted candidate: an effect added to the model, or a learned density replacing its density.

    Attributes:
        name: ``effect``, ``effect(option=choice)`` or a density's name.
        k: scalar parameters added (for a learned density: the entries of its tables).
        train_gain: log-likelihood gain on the rays it was fitted on, nats (total).
        test_gain: held-out NLL decrease, nats per ray.
        test_gain_pct: the same relative to the model's held-out NLL, percent (NaN when that NLL
            is within 1 nat/ray of zero, see :func:`relative_gain`).
        lr: training likelihood-ratio statistic ``2 train_gain`` (reported, not used).
        p_value: one-sided p-value of the held-out paired test of the per-ray gains.
        delta_bic: ``k ln n - lr`` on the fitting rays (reported, not used).
        significant: ``p_value`` below the round's threshold and a held-out gain of at least :data:`MIN_GAIN`.
        parameters: fitted values (of the candidate fit).
        status: :data:`JOINED`, :data:`LOST` (significant alone, not once the model's effects were
            refitted with it), :data:`DROPPED` (it joined, but the final joint refit left it no
            held-out gain), :data:`REPLACED` (a learned density beat the model with the effects found),
            :data:`FAILED` (its joint refit failed: not finite) or ``""``.
        kind: ``effect`` or ``density``.
        history: training mean log-likelihood per step, nats/ray.
        effect: the fitted effect or density.
        test_ll: (N,) held-out per-ray log-likelihood of the model with the candidate, nats.
    """

    name: str
    k: int
    train_gain: float
    test_gain: float
    test_gain_pct: float
    lr: float
    p_value: float
    delta_bic: float
    significant: bool
    parameters: dict
    status: str = ""
    kind: str = "effect"
    history: list = field(repr=False, default_factory=list)
    effect: object = field(repr=False, default=None)
    test_ll: np.ndarray = field(repr=False, default=None)

    def row(self) -> dict:
        hidden = ("effect", "history", "test_ll")
        return {k: getattr(self, k) for k in (f.name for f in dataclasses.fields(self)) if k not in hidden} | {
            "parameters": {k: json_value(v) for k, v in self.parameters.items()}
        }


def json_value(value):
    """A fitted parameter's value as JSON (a candidate's row, the diagnosis' values): numbers rounded to 6 decimals,
    options (text, such as P-Reg's escape law in its chosen setting) as they are, lists and arrays element by
    element."""
    if isinstance(value, str):
        return value
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    array = np.asarray(value)
    return np.round(array.astype(float), 6).tolist() if array.dtype.kind in "biuf" else array.tolist()


def rank(candidates: list[Candidate]) -> list[Candidate]:
    """Candidates best first: by held-out gain; while a candidate with fewer parameters is not beaten by the
    leader in the paired held-out test at :data:`P_VALUE`, the best of those simpler ones leads instead."""
    ranked = sorted(candidates, key=lambda c: -c.test_gain)
    while ranked:
        leader = ranked[0]
        equal = [c for c in ranked[1:] if c.k < leader.k and held_out_test(leader.test_ll, c.test_ll)[1] >= P_VALUE]
        if not equal:
            break
        ranked.remove(equal[0])
        ranked.insert(0, equal[0])
    return ranked


def default_posterior(z: np.ndarray, informative: np.ndarray | None = None) -> np.ndarray:
    """Probability that each per-beam value is at its default, judged from every beam's at once.

    Each value's statistic ``z = sqrt(2 LR)`` (LR: its log-likelihood ratio against the default) is modelled
    as the two-group mixture ``pi0 N(0, 1) + (1 - pi0) N(0, s^2)`` in ``|z|``: beams at the default, and beams
    off it whose values spread ``s`` standard errors. ``pi0`` and ``s`` are the maximum-likelihood values on a
    grid (``s`` from the chi-square(1) critical ``z`` at :data:`P_VALUE` up, so that the off-default group is one
    a test could tell from the default; ties go to the larger ``pi0``), fitted on the ``informative`` values
    (those whose rays depend on them: a beam that returned nothing says nothing of how many values are at
    the default). On a log with no effect ``pi0`` is 1 and every value is at its default; with a bias on
    every beam ``pi0`` is near 0 and a beam whose bias is within its noise of 0 keeps its value.

    Args:
        z: (B,) statistics of the values (sign ignored).
        informative: (B,) bool, the values the mixture is fitted on (default: all).

    Returns:
        (B,) posterior probabilities of the default.
    """
    z = np.abs(np.asarray(z, np.float64))
    lowest = math.sqrt(float(stats.chi2.isf(P_VALUE, 1)))
    pi0 = np.linspace(1.0, 0.0, 101)[:, None, None]
    spread = np.geomspace(lowest, max(2.0 * float(z.max(initial=0.0)), 2.0 * lowest), 80)[None, :, None]  # in z
    at_default = stats.norm.pdf(z)
    mixture = pi0 * at_default + (1.0 - pi0) * stats.norm.pdf(z / spread) / spread
    fitted = np.log(np.maximum(mixture, 1e-300))[..., slice(None) if informative is None else informative]
    i, j = np.unravel_index(np.argmax(fitted.sum(-1)), mixture.shape[:2])
    return pi0[i, 0, 0] * at_default / np.maximum(mixture[i, j], 1e-300)


def shrink_without_evidence(model: SensorModel, effects: list, problem: Problem) -> None:
    """Set per-beam / per-label values without evidence back to their default (in place).

    A value has evidence when setting it to the parameter's default lowers the log-likelihood of
    ``problem`` by more than half the chi-square(1) critical value at :data:`P_VALUE`. A per-beam value
    acts on its beam's rays alone, so every beam's is judged at once from two evaluations (its values and
    the defaults, summed beam by beam: :meth:`~mi_lidar.core.problem.Problem.log_likelihood_by_beam`), and a value
    below the critical ratio stays when :func:`default_posterior` puts it off its default (a bias on every beam:
    zeroing each one within 3.3 standard errors of 0 made the 360 fitted biases of a planar log 4.95 % off the
    truth instead of 3.90 %); the per-label values are set back one at a time (a ray may meet elements of
    several labels).
    """
    critical = 0.5 * float(stats.chi2.isf(P_VALUE, 1))

    def assign(effect, key: str, values: np.ndarray) -> None:
        effect.params[key] = mi.Float(aligned(values))
        make_opaque([effect])

    for effect in effects:
        for key in effect.fitted_names():
            spec = effect.specs[key]
            if not (spec.per_beam or spec.per_label) or spec.default is None:
                continue
            values = np.asarray(effect.params[key], np.float32).copy()
            if spec.per_beam:
                full = problem.log_likelihood_by_beam(model, values.size)
                assign(effect, key, np.full_like(values, spec.default))
                reduced = problem.log_likelihood_by_beam(model, values.size)
                ratio = full - reduced
                z = np.sqrt(2.0 * np.maximum(ratio, 0.0))
                values[(ratio < critical) & (default_posterior(z, ratio != 0.0) > 0.5)] = spec.default
                assign(effect, key, values)
                continue
            full = float(problem.log_likelihood(model).sum())
            for i in np.flatnonzero(values != spec.default):
                trial = values.copy()
                trial[i] = spec.default
                assign(effect, key, trial)
                reduced = float(problem.log_likelihood(model).sum())
                if full - reduced < critical:
                    values, full = trial, reduced
            assign(effect, key, values)


def drop_passengers(base: SensorModel, added: list, test: Problem, names: list[str]) -> tuple[SensorModel, list]:
    """Remove the added effects that no longer win held out once every effect is refitted together.

    Each effect, in the order they joined, is dropped when the model without it is not significantly
    worse held out (the one test, at :data:`P_VALUE`). The first is tested too: it joined alone, and may
    have stood in for the effects that joined after it (a noise law that, joined first, took up a range
    scale and a per-beam bias as spread, and is left with nothing once they joined).

    Args:
        base: the final model (refitted).
        added: the effects that joined during this diagnosis, in order.
        test: the held-out rays.
        names: the candidate names of ``added``.

    Returns:
        The model without the dropped effects, and the names of the dropped ones.
    """
    full = test.log_likelihood(base)
    dropped = []
    for effect, name in zip(added, names):
        without = dataclasses.replace(base, effects=[e for e in base.effects if e is not effect])
        gain, p = held_out_test(full, test.log_likelihood(without))
        if significant(gain, p, P_VALUE):
            continue
        base, full = without, test.log_likelihood(without)
        dropped.append(name)
    return base, dropped
