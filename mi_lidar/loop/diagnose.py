"""Which effect is missing? Fit every candidate on training rays, confirm it on held-out rays.

:func:`diagnose` reads as its steps:

1. **split** the log's rays into training and held-out rays (:func:`~mi_lidar.loop.split.split_rays`);
   candidates are fitted on a subsample of the training rays. Each split is traced once in the
   scene and reused by every candidate and round (:class:`~mi_lidar.core.problem.Problem` traces
   again only for effects that move rays).
2. **screen**: each round (:class:`~mi_lidar.loop.rounds.Round`), every effect of the catalog
   (:mod:`mi_lidar.loop.catalog`) is added to the model, fitted on the subsample
   (:func:`~mi_lidar.loop.catalog.refit`) and scored on every held-out ray; candidates are ranked by
   held-out gain per ray, a simpler candidate first when the best does not beat it significantly
   (:func:`~mi_lidar.loop.selection.rank`). Screening fits stop once they stop gaining, so the effects
   in a close race with the leader are fitted to the end before the ranking decides.
3. **join**: the best significant candidate that still wins held out after the model's effects are
   refitted with it joins (:mod:`mi_lidar.loop.selection`: one test for the tables and the verdict).
   Rounds repeat until nothing joins (``rounds`` at most, when given); after the first round only the
   candidates that were significant in it are tried again (an effect that does not improve the model
   alone is not looked for behind another), so there are at most as many rounds as those.
4. **realism**: with every joined effect the model is sampled at the held-out rays before and after
   (the same random numbers), and the realism of the samples is put beside the NLL (median and p90
   |range error|, return rate, hit/miss F1, histogram match; :func:`~mi_lidar.core.metrics.metrics_of`);
   :func:`~mi_lidar.loop.realism.realism_warning` says so when an effect buys likelihood with samples
   that are clearly worse.
5. **final fit**: every effect is refitted together on the whole training split; effects left
   without held-out gain are dropped, per-beam or per-label values without evidence shrunk. Once the
   final model is scored and its residuals tested on the held-out rays, the values it reports are
   refitted on every ray of the log (training and held-out: twice the data, so about 1/sqrt(2) of
   the error of a half-log fit); the held-out figures stay those of the training fit.
6. **learned densities**: when the given model has no effects, the thesis's learned densities
   (NP-Reg, P-Reg) replace its density and are held against the model with the effects found; one
   replaces that model only when it beats it significantly, by 0.01 nats/ray at least (a physical
   effect says why, a learned density only what, so it wins only what no combination of catalog
   effects explains: a skewed residual, say).
7. **what is left**: the residuals of the final model are tested for structure along time, azimuth,
   beam, range and label (:mod:`mi_lidar.loop.residuals`): what varies there no catalog effect explains.
8. **report**: :mod:`mi_lidar.loop.diagnosis_report` (Markdown, HTML, JSON and figures).

A candidate whose fit fails (:class:`~mi_lidar.core.errors.FitError`: its loss or gradient is not finite) is
left out of its round and of the rounds after, and named with the reason in :attr:`Diagnosis.failed`, the
verdict and the report; the other candidates go on (a failed screening fit once cost a 7-minute run). A refit outside
the rounds that fails (of the given model's effects before screening; the final joint refit, the refit after dropping
passengers, the refit on every ray) leaves the effects at the values they had before it and is named the same way; the
report is written.

Scores are floored per ray with the one floor of :func:`~mi_lidar.core.likelihood.score`.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import output_folder
from mi_lidar.core.errors import FitError
from mi_lidar.core.log import Log
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.catalog import DENSITY_CANDIDATES, candidate_names, candidate_settings, refit_or_keep
from mi_lidar.loop.compare import RayTable, first_elements, gain_groups
from mi_lidar.loop.intensity_residuals import intensity_residuals, intensity_section
from mi_lidar.loop.realism import Realism
from mi_lidar.loop.residuals import residual_structure
from mi_lidar.loop.rounds import Round, candidate_label, learned_densities
from mi_lidar.loop.selection import (
    DROPPED,
    JOINED,
    P_VALUE,
    REPLACED,
    drop_passengers,
    json_value,
    rank,
    shrink_without_evidence,
)
from mi_lidar.loop.split import Splits

SIMULATION_STREAM = 7  # seed offset of the samples drawn for realism (the same for every model compared)
MIN_ESTIMATION_RAYS = 1000  # training rays beyond the fitting subsample a learned density needs
KEPT = "the effects keep the values they had before it"  # what a refit outside the rounds that failed leaves
TRAINING_VALUES = "the values reported are those fitted on the training rays"  # ... when it was the one on every ray


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes:
        rounds: per round, the candidates ranked best first.
        selected: names of the candidates that joined, in order.
        nll_before, nll_after: held-out NLL per ray of the given and of the final model.
        evidence: per joined candidate, the breakdown groups where its gain concentrates and the rows of
            ``realism`` before and after it joined.
        summary: the plain-words verdict, in Markdown (the missing effect's name in bold: ``**name**``).
        parameters: the final model's fitted values of the selected effects, ``{"effect.param": values}``,
            refitted on every ray of the log once the held-out figures were taken.
        structure: residual structure left by the final model (:class:`~mi_lidar.loop.residuals.Structure`).
        realism: the given model, the model after each joined candidate, and the final model
            (:class:`~mi_lidar.loop.realism.Realism`, held-out rays).
        held_out: the held-out rays described (first element, beam, azimuth...), for the figures.
        model: the augmented, fitted model.
        density: the learned density that joined and replaced the model's (None when none did).
        failed: the candidate fits that failed, ``{"candidate", "round", "stage", "reason"}`` each
            (:class:`~mi_lidar.core.errors.FitError`); those candidates were left out. A refit outside the rounds
            that failed has round None, the effects refitted as ``candidate`` and ``kept``: what the model kept.
    """

    rounds: list
    selected: list
    nll_before: float
    nll_after: float
    evidence: list
    summary: str
    parameters: dict = field(default_factory=dict)
    structure: list = field(default_factory=list)
    realism: list = field(default_factory=list)
    held_out: RayTable | None = field(repr=False, default=None)
    model: SensorModel = field(repr=False, default=None)
    density: object = field(repr=False, default=None)
    failed: list = field(default_factory=list)

    def ranking(self) -> list[dict]:
        """The first round's ranking as JSON-able rows."""
        return [c.row() for c in self.rounds[0]] if self.rounds else []

    def flagged(self) -> list[str]:
        """Dimensions along which the final model's residuals still vary."""
        return [s.dimension for s in self.structure if s.flagged]

    def warnings(self) -> list[str]:
        """The realism warnings of the joined candidates."""
        return [r.warning for r in self.realism if r.warning]

    def to_json(self) -> dict:
        return {
            "selected": self.selected,
            "nll_before": self.nll_before,
            "nll_after": self.nll_after,
            "parameters": {k: json_value(v) for k, v in self.parameters.items()},
            "rounds": [[c.row() for c in r] for r in self.rounds],
            "evidence": self.evidence,
            "realism": [r.row() for r in self.realism],
            "structure": [s.row() for s in self.structure],
            "failed": self.failed,
            "summary": self.summary,
        }


def diagnose(
    log: Log,
    scene,
    model: SensorModel | None = None,
    out: str | Path | None = None,
    candidates: list[str] | None = None,
    steps: int = 60,
    rounds: int | None = None,
    max_train: int = 200_000,
    max_test: int = 200_000,
    max_fit: int = 20_000,
    seed: int = 0,
    progress=None,
    force: bool = False,
) -> Diagnosis:
    """Find the effects missing from ``model`` on ``log``, confirmed on held-out rays.

    Args:
        log: measured log.
        scene: loaded Mitsuba scene or scene XML path.
        model: the current sensor model (default: the scene's); its effects are refitted first.
        out: folder for ``diagnosis.json``, ``diagnosis.md``, ``diagnosis.html`` and the figures
            (nothing written when None).
        candidates: effects (or learned densities, :data:`~mi_lidar.loop.catalog.DENSITY_CANDIDATES`)
            to try, named with dashes or underscores, or as the ranking prints them
            (``incidence_dropout(law=cos)``, :func:`~mi_lidar.loop.catalog.parse_candidate`) (default:
            every registered effect not in the model, and the learned densities when the model has no effects).
        steps: Adam steps per fit at most (screening fits stop once they stop gaining; the final joint
            refit takes twice as many).
        rounds: selection rounds at most, so candidates joined at most (None: until no candidate joins).
        max_train, max_test: rays per split (random subsample beyond).
        max_fit: training rays each candidate is fitted on (a subsample of the training split).
        seed: subsampling and simulation seed.
        progress: optional callable ``progress(done, total, label)``.
        force: diagnose even when the log's sensor does not match the scene's.

    Returns:
        The :class:`Diagnosis`.

    Raises:
        SensorMismatchError: the log was recorded by another sensor than the scene's
            (:func:`~mi_lidar.scene.sensor_check.check_log_sensor`).
    """
    from mi_lidar.loop.diagnosis_report import verdict, write_report
    from mi_lidar.scene.loading import scene_sensor_model
    from mi_lidar.scene.sensor_check import log_scene, scene_warnings

    scene = log_scene(log, scene, force)
    base = copy.deepcopy(model or scene_sensor_model(scene)[0])
    data = Splits.build(log, scene, max_train, max_test, max_fit, seed)
    failed: list = []
    if base.effects:  # the given model's own effects, fitted before the candidates are screened beside them
        given_effects = [(e.name, e) for e in base.effects]
        _guarded_refit(base, data.train, steps, "refit before screening", given_effects, failed)
    data.describe(base)
    stream = seed + SIMULATION_STREAM
    realism = [data.realism(base, "given model", stream)]
    before_test = realism[0].ll
    nll_before = float(-before_test.mean())
    names = candidate_settings(base.effects, candidates, not base.effects)
    densities = [n for n, _ in names if n in DENSITY_CANDIDATES] if not base.effects else []
    too_few = bool(densities) and data.estimation.n < MIN_ESTIMATION_RAYS
    if too_few:  # a learned density is estimated on training rays the screening fits do not use
        densities = []
    names = [(n, v) for n, v in names if n not in DENSITY_CANDIDATES]
    given = copy.deepcopy(base)
    all_rounds, selected, evidence, joined_effects = [], [], [], []
    total, done = len(names) + len(densities), 0
    for round_number in range(1, (len(names) if rounds is None else rounds) + 1):
        if not names:
            break
        total = done + len(names) + len(densities)  # this round's candidates: later rounds add theirs when they start
        base_fit = float(data.fitting.log_likelihood(base).sum())
        this_round = Round(base, data, steps, P_VALUE / len(names), nll_before, before_test, base_fit)
        ranked, failures = [], []  # failures: (candidate, stage, reason) of this round
        for name, variant in names:
            label = candidate_label(name, variant)
            try:
                ranked.append(this_round.screen(name, variant))
            except FitError as error:
                failures.append((label, "screening", str(error)))
                label += ": fit failed, left out"
            done += 1
            if progress is not None:
                progress(done, total, label)
        ranked = rank(this_round.converged(rank(ranked), failures))
        all_rounds.append(ranked)
        joined, augmented, after_test = this_round.join(ranked, failures)
        failed += [{"candidate": c, "round": round_number, "stage": stage, "reason": why} for c, stage, why in failures]
        names = [(n, v) for n, v in names if candidate_label(n, v) not in {c for c, _, _ in failures}]  # not again
        if joined is None:
            break
        groups = gain_groups(data.held_out, before_test, after_test)
        evidence.append({"effect": joined.name, "groups": groups, "realism": [len(realism) - 1, len(realism)]})
        realism.append(data.realism(augmented, f"+ {joined.name}", stream, realism[-1]))
        joined_effects.append((joined.name, augmented.effects[-1]))
        base, before_test = augmented, after_test
        selected.append(joined.name)
        if len(all_rounds) == 1:  # later rounds retry only what was significant alone
            names = [(n, v) for n, v in names if candidate_label(n, v) in {c.name for c in ranked if c.significant}]
        kept = set(candidate_names(base.effects, [n for n, _ in names]))
        names = [(n, v) for n, v in names if n in kept]
    if joined_effects:
        _guarded_refit(base, data.train, 2 * steps, "final joint refit", joined_effects, failed)
        added = [e for _, e in joined_effects]
        base, dropped = drop_passengers(base, added, data.test, [n for n, _ in joined_effects])
        for c in (c for r in all_rounds for c in r if c.name in dropped and c.status == JOINED):
            c.status = DROPPED
        selected = [n for n in selected if n not in dropped]
        joined_effects = [(n, e) for n, e in joined_effects if n not in dropped]
        if dropped:
            _guarded_refit(
                base, data.train, steps, f"refit after dropping {', '.join(dropped)}", joined_effects, failed
            )
        shrink_without_evidence(base, [e for _, e in joined_effects], data.train)
    if selected:
        realism.append(data.realism(base, "final model", stream, None))
    if densities:
        learned = learned_densities(densities, given, base, data, realism[-1])
        all_rounds.append(learned)
        done += len(densities)
        if progress is not None:
            progress(done, total, "learned densities")
        if learned and learned[0].status == JOINED:
            for c in (c for r in all_rounds for c in r if c.status == JOINED and c.kind == "effect"):
                c.status = REPLACED
            base, selected, joined_effects = (
                dataclasses.replace(given, density=learned[0].effect),
                [learned[0].name],
                [],
            )
            groups = gain_groups(data.held_out, realism[-1].ll, learned[0].test_ll)
            evidence.append({"effect": learned[0].name, "groups": groups, "realism": [len(realism) - 1, len(realism)]})
            realism.append(data.realism(base, f"{learned[0].name} instead", stream, realism[-1]))
    final = realism[-1]
    structure = _structure(data, base, final)
    if joined_effects:  # the held-out figures are taken: report values fitted on every ray
        whole = data.whole()
        if _guarded_refit(base, whole, steps, "refit on every ray", joined_effects, failed, TRAINING_VALUES):
            shrink_without_evidence(base, [e for _, e in joined_effects], whole)
    result = Diagnosis(
        rounds=all_rounds,
        selected=selected,
        nll_before=nll_before,
        nll_after=float(-final.ll.mean()),
        evidence=evidence,
        summary="",
        parameters={
            f"{e.name}.{key}": np.asarray(e.params[key]) for _, e in joined_effects for key in e.fitted_names()
        },
        structure=structure,
        realism=realism,
        held_out=data.held_out,
        model=base,
        failed=failed,
        density=next((c.effect for r in all_rounds for c in r if c.kind == "density" and c.status == JOINED), None),
    )
    result.summary = verdict(result)
    for warning in scene_warnings(data.test.near_surface(base), data.rays.hit[data.test.index]):
        result.summary = f"Warning: {warning}. {result.summary}"
    if too_few:
        result.summary += (
            f" The learned densities were not tried: they are estimated on the training rays beyond the "
            f"{data.fitting.n:,} the screening fits use, and this log has {data.estimation.n:,} of them "
            f"(at least {MIN_ESTIMATION_RAYS:,} needed): record a longer log (more scans), or, from Python, pass "
            "mi_lidar.loop.diagnose a smaller max_fit."
        )
    if out is not None:
        out = Path(out)
        with output_folder(out):  # a first write that fails (a full disk) leaves no empty folder behind
            intensity = intensity_section(intensity_residuals(log, data.scene, base, data.test.index), out)
            write_report(result, out, appendix=intensity)
    return result


def _guarded_refit(model, problem, steps: int, stage: str, found: list, failed: list, kept: str = KEPT) -> bool:
    """Refit the effects ``found`` (``(name, effect)`` pairs) of ``model``; a fit that fails leaves them as they were
    (:func:`~mi_lidar.loop.catalog.refit_or_keep`).

    Returns:
        Whether the refit went through; when it did not, ``failed`` has an entry naming ``stage``, the effects, the
        reason and ``kept`` (round None).
    """
    error = refit_or_keep(model, problem, steps)
    if error is not None:
        names = ", ".join(name for name, _ in found)
        failed.append({"candidate": names, "round": None, "stage": stage, "reason": str(error), "kept": kept})
    return error is None


def _structure(data: Splits, model: SensorModel, final: Realism) -> list:
    """Residual structure of ``model`` on the held-out rays (:func:`~mi_lidar.loop.residuals.residual_structure`)."""
    index = data.test.index
    first = first_elements(data.scene, data.table, data.test, model)
    dimensions = {
        "time": data.rays.time[index],
        "azimuth": data.held_out.azimuth,
        "beam": data.rays.beam[index],
        "range": first["nominal"],
        "label": np.where(first["label"] >= 0, first["label"], np.nan),
    }
    measured, hit = data.rays.measured[index], data.rays.hit[index]
    return residual_structure(dimensions, first["nominal"], measured, hit, final.sim_range, final.sim_hit)
