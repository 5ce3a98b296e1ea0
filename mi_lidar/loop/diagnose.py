"""Which effect is missing? Fit every candidate on training rays, confirm it on held-out rays.

For each catalog effect (and every user-registered effect) not yet in the model, and for each
choice of its variant options, :func:`diagnose` adds the effect to the model, fits its parameters
on a subsample of the training split (:func:`~mi_lidar.core.problem.fit_parts`) and scores every
held-out ray. One test decides everything the report says:

* **held-out significance**: the per-ray gains of the held-out log-likelihood (candidate minus
  current model) are tested with a one-sided paired z-test; a candidate is *significant* when
  ``p < P_VALUE / candidates`` (Bonferroni over the round's candidates) and its mean gain is at
  least :data:`MIN_GAIN` (smaller gains on a large log are significant but are the leftovers of an
  imperfect fit of the effects already found, not a new physical effect). The training likelihood
  ratio and BIC change are reported beside it, not used.

Candidates are ranked by held-out gain per ray. A significant candidate **joins** the model only
when, after every effect of the augmented model is refitted together (on the same subsample), the
augmented model still beats the current one held out by the same test; otherwise the next
significant candidate is tried. Rounds repeat (``rounds`` at most) until no candidate joins; after
the first round only the candidates that were significant in it are tried again (an effect that
does not improve the model alone is not looked for behind another). Then the model gets a final
joint refit on the whole training split, and per-beam or per-label values without evidence (their
likelihood ratio against the parameter's default below the chi-square(1) critical value) are set
back to the default; an effect that joined only to take up what an earlier one had not yet fitted,
and has no held-out gain after the final refit, is dropped. Last, the residuals of the final model
are tested for structure along time, azimuth, beam, range and label
(:mod:`mi_lidar.loop.residuals`): what varies there is something no catalog effect explains.

The scene is traced once per split and model rays (:meth:`~mi_lidar.core.problem.Problem.trace`
re-traces only for effects that move rays). Scores are floored per ray with the one floor of
:func:`~mi_lidar.core.likelihood.score`.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np
from scipy import stats

from mi_lidar.core.arrays import aligned
from mi_lidar.core.atomic import atomic_write
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.core.problem import Problem, fit_parts, make_opaque, n_parameters
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.io.markdown import markdown_to_html
from mi_lidar.loop.catalog import candidate, candidate_names, variants
from mi_lidar.loop.compare import BREAKDOWNS, RayTable, first_elements, group_keys, simulate_log_rays
from mi_lidar.loop.intensity_residuals import intensity_residuals, intensity_section
from mi_lidar.loop.residuals import plot_structure, residual_structure, structure_verdict

P_VALUE = 1e-3
MIN_GAIN = 0.01  # nats/ray: the smallest held-out gain that counts as a missing effect
MIN_NLL_FOR_PERCENT = 1.0  # nats/ray: below this a gain relative to the NLL is not meaningful


def relative_gain(gain: float, nll: float) -> float:
    """``gain`` as a percentage of ``|nll|`` (NaN when ``|nll| < MIN_NLL_FOR_PERCENT``).

    An NLL per ray is a log-density: its zero depends on the range unit and bin, so a percentage
    of a value near zero says nothing; the absolute gain in nats/ray is the measure then.
    """
    return 100.0 * gain / abs(nll) if abs(nll) >= MIN_NLL_FOR_PERCENT else float("nan")


def split_rays(log: Log, max_train: int, max_test: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out ray indices: alternate scans, or alternate blocks of 64 columns of one scan
    (64 beams when the scan has more beams than columns, e.g. a planar scan of N beams x 1 firing).

    Each split is subsampled (without replacement, fixed ``seed``) to at most its maximum.

    Raises:
        LogFormatError: one scan too small to hold out a block (65 columns or beams at least).
    """
    s, h, w = log.shape
    scan, beam, column = np.meshgrid(np.arange(s), np.arange(h), np.arange(w), indexing="ij")
    train = (scan.ravel() % 2 == 0) if s > 1 else (((column if w >= h else beam).ravel() // 64) % 2 == 0)
    if train.all():
        raise LogFormatError(
            f"the log holds one scan of {h} beams x {w} firings: too few to hold out a block of 64 rays; "
            "give a log of two scans or more"
        )
    rng = np.random.default_rng(seed)

    def cap(index, size):
        return np.sort(rng.choice(index, size, replace=False)) if index.size > size else index

    return cap(np.flatnonzero(train), max_train), cap(np.flatnonzero(~train), max_test)


@dataclass
class Candidate:
    """One fitted candidate effect.

    Attributes:
        name: ``effect`` or ``effect(option=choice)``.
        k: scalar parameters added.
        train_gain: log-likelihood gain on the rays it was fitted on, nats (total).
        test_gain: held-out NLL decrease, nats per ray.
        test_gain_pct: the same relative to the model's held-out NLL, percent (NaN when that NLL
            is within 1 nat/ray of zero, see :func:`relative_gain`).
        lr: training likelihood-ratio statistic ``2 train_gain`` (reported, not used).
        p_value: one-sided p-value of the held-out paired test of the per-ray gains.
        delta_bic: ``k ln n - lr`` on the fitting rays (reported, not used).
        significant: ``p_value`` below the round's threshold and a held-out gain of at least :data:`MIN_GAIN`.
        status: ``joined``, ``lost in the joint refit`` (significant alone, not once the model's
            effects were refitted with it), ``dropped after the final refit`` (it joined, but the
            final joint refit left it no held-out gain) or ``""``.
        parameters: fitted values (of the candidate fit).
        history: training mean log-likelihood per step, nats/ray.
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
    history: list = field(repr=False, default_factory=list)
    effect: object = field(repr=False, default=None)

    def row(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if k not in ("effect", "history")} | {
            "parameters": {k: np.round(np.asarray(v, dtype=float), 6).tolist() for k, v in self.parameters.items()}
        }


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`.

    Attributes:
        rounds: per round, the candidates ranked best first.
        selected: names of the effects that joined, in order.
        nll_before, nll_after: held-out NLL per ray of the given and of the final model.
        evidence: per selected effect, the breakdown groups where its gain concentrates.
        summary: the plain-words verdict.
        parameters: the final model's fitted values of the selected effects, ``{"effect.param": values}``.
        structure: residual structure left by the final model (:class:`~mi_lidar.loop.residuals.Structure`).
        model: the augmented, fitted model.
    """

    rounds: list
    selected: list
    nll_before: float
    nll_after: float
    evidence: list
    summary: str
    parameters: dict = field(default_factory=dict)
    structure: list = field(default_factory=list)
    model: SensorModel = field(repr=False, default=None)

    def ranking(self) -> list[dict]:
        """The first round's ranking as JSON-able rows."""
        return [c.row() for c in self.rounds[0]] if self.rounds else []

    def flagged(self) -> list[str]:
        """Dimensions along which the final model's residuals still vary."""
        return [s.dimension for s in self.structure if s.flagged]

    def to_json(self) -> dict:
        return {
            "selected": self.selected,
            "nll_before": self.nll_before,
            "nll_after": self.nll_after,
            "parameters": {k: np.round(np.asarray(v, float), 6).tolist() for k, v in self.parameters.items()},
            "rounds": [[c.row() for c in r] for r in self.rounds],
            "evidence": self.evidence,
            "structure": [s.row() for s in self.structure],
            "summary": self.summary,
        }


def _label(name: str, variant: dict) -> str:
    """``effect`` or ``effect(option=choice)``: a candidate's name in the tables."""
    return name + (f"({', '.join(f'{key}={v}' for key, v in variant.items())})" if variant else "")


def held_out_test(after: np.ndarray, before: np.ndarray) -> tuple[float, float]:
    """Mean per-ray gain (nats) of ``after`` over ``before`` and the one-sided p-value of the paired z-test."""
    diff = after - before
    gain = float(diff.mean())
    error = float(diff.std(ddof=1) / math.sqrt(diff.size)) if diff.size > 1 else 0.0
    if error == 0.0:
        return gain, 0.0 if gain > 0 else 1.0
    return gain, float(stats.norm.sf(gain / error))


def shrink_without_evidence(model: SensorModel, effects: list, problem: Problem) -> None:
    """Set per-beam / per-label values without evidence back to their default (in place).

    A value has evidence when setting it to the parameter's default lowers the log-likelihood of
    ``problem`` by more than half the chi-square(1) critical value at :data:`P_VALUE`.
    """
    critical = 0.5 * float(stats.chi2.isf(P_VALUE, 1))
    for effect in effects:
        for key in effect.fitted_names():
            spec = effect.specs[key]
            if not (spec.per_beam or spec.per_label) or spec.default is None:
                continue
            values = np.asarray(effect.params[key], np.float32).copy()
            full = float(problem.log_likelihood(model).sum())
            for i in np.flatnonzero(values != spec.default):
                trial = values.copy()
                trial[i] = spec.default
                effect.params[key] = mi.Float(aligned(trial))
                if full - float(problem.log_likelihood(model).sum()) < critical:
                    values = trial
                    full = float(problem.log_likelihood(model).sum())
            effect.params[key] = mi.Float(aligned(values))
            make_opaque([effect])


def _evidence(test: Problem, model_before: SensorModel, model_after: SensorModel, table: RayTable) -> list[dict]:
    """The breakdown groups where the held-out gain of a new effect concentrates most."""
    test.trace(model_before)
    before = test.log_likelihood(model_before)
    test.trace(model_after)
    after = test.log_likelihood(model_after)
    rows = []
    for by in BREAKDOWNS:
        keys = group_keys(table, by)
        groups = np.unique(keys)
        if len(groups) < 2:
            continue
        for key in groups:
            m = keys == key
            gain = float(np.sum(after[m] - before[m]))
            rows.append(
                {
                    "breakdown": by,
                    "group": str(key),
                    "rays": int(m.sum()),
                    "gain": gain,
                    "nll_before": float(-before[m].mean()),
                    "nll_after": float(-after[m].mean()),
                }
            )
    best = {}
    for row in sorted(rows, key=lambda r: -(r["nll_before"] - r["nll_after"])):
        if row["rays"] >= 0.02 * before.size and row["breakdown"] not in best:
            best[row["breakdown"]] = row
    return sorted(best.values(), key=lambda r: -(r["nll_before"] - r["nll_after"]))[:3]


def diagnose(
    log: Log,
    scene,
    model: SensorModel | None = None,
    out: str | Path | None = None,
    candidates: list[str] | None = None,
    steps: int = 60,
    rounds: int = 3,
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
        out: folder for ``diagnosis.json``, ``diagnosis.md``, ``diagnosis.html`` and ``residual_structure.png``
            (nothing written when None).
        candidates: effect names to try (default: every registered effect not in the model).
        steps: Adam steps per fit (the final joint refit takes twice as many).
        rounds: selection rounds (effects added at most).
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
    from mi_lidar.scene.loading import load_scene, scene_sensor_model
    from mi_lidar.scene.sensor_check import check_log_sensor

    if not hasattr(scene, "shapes"):
        scene = load_scene(scene)
    check_log_sensor(log, scene, force=force)
    base = copy.deepcopy(model or scene_sensor_model(scene)[0])
    rays = LogRays.from_log(log)
    train_index, test_index = split_rays(log, max_train, max_test, seed)
    fit_index = np.sort(np.random.default_rng(seed + 1).permutation(train_index)[:max_fit])
    table = ElementTable.from_scene(scene)
    train = Problem.build(scene, rays, train_index, table)
    fitting = Problem.build(scene, rays, fit_index, table)
    test = Problem.build(scene, rays, test_index, table)
    n_beams, n_labels = log.shape[1], int(np.asarray(train.table.label).max()) + 1
    if base.effects:
        fit_parts(base, train, steps=steps)
    scan_of = rays.scan[test_index] if log.directions.shape[0] > 1 else np.zeros(test_index.size, int)
    d = log.directions[scan_of, rays.beam[test_index], rays.column[test_index]]
    azimuth = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    first = first_elements(scene, test.table, test, base)
    table = RayTable(
        ll=np.zeros(test_index.size),
        measured=rays.measured[test_index],
        hit=rays.hit[test_index],
        sim_range=rays.measured[test_index],
        sim_hit=rays.hit[test_index],
        beam=rays.beam[test_index],
        column=rays.column[test_index],
        scan=rays.scan[test_index],
        azimuth=azimuth,
        **first,
    )
    before_test = test.log_likelihood(base)
    nll_before = float(-before_test.mean())
    all_rounds, selected, evidence = [], [], []
    names = [(n, v) for n in candidate_names(base.effects, candidates) for v in variants(n)]
    total, done = len(names) * rounds, 0
    for _ in range(rounds):
        if not names:
            break
        threshold = P_VALUE / len(names)
        base_fit = float(fitting.log_likelihood(base).sum())
        ranked = []
        for name, variant in names:
            effect = candidate(name, n_beams, n_labels, **variant)
            trial = dataclasses.replace(base, effects=base.effects + [effect])
            fit = fit_parts(trial, fitting, [effect], steps=steps)
            k = n_parameters([effect])
            gain_fit = float(fitting.log_likelihood(trial).sum()) - base_fit
            lr = max(2.0 * gain_fit, 0.0)
            gain, p = held_out_test(test.log_likelihood(trial), before_test)
            label = _label(name, variant)
            ranked.append(
                Candidate(
                    name=label,
                    k=k,
                    train_gain=gain_fit,
                    test_gain=gain,
                    test_gain_pct=relative_gain(gain, nll_before),
                    lr=lr,
                    p_value=p,
                    delta_bic=k * math.log(fit_index.size) - lr,
                    significant=bool(p < threshold and gain >= MIN_GAIN),
                    parameters=fit.parameters,
                    history=fit.history,
                    effect=effect,
                )
            )
            done += 1
            if progress is not None:
                progress(done, total, label)
        ranked.sort(key=lambda c: -c.test_gain)
        all_rounds.append(ranked)
        joined = None
        for c in (c for c in ranked if c.significant):
            augmented = dataclasses.replace(base, effects=base.effects + [copy.deepcopy(c.effect)])
            fit_parts(augmented, fitting, steps=steps)  # earlier effects adapt to the new one
            after_test = test.log_likelihood(augmented)
            gain, p = held_out_test(after_test, before_test)
            if p < threshold and gain >= MIN_GAIN:
                joined = c
                break
            c.status = "lost in the joint refit"
        if joined is None:
            break
        joined.status = "joined"
        evidence.append({"effect": joined.name, "groups": _evidence(test, base, augmented, table)})
        base, before_test = augmented, after_test
        selected.append(joined.name)
        chosen = joined.name.split("(")[0]
        if len(all_rounds) == 1:  # later rounds retry only what was significant alone
            significant = {c.name for c in ranked if c.significant}
            names = [(n, v) for n, v in names if _label(n, v) in significant]
        names = [(n, v) for n, v in names if n != chosen]
    added = base.effects[len(base.effects) - len(selected) :] if selected else []
    if selected:
        fit_parts(base, train, steps=2 * steps)
        base, added = _drop_passengers(base, added, test, all_rounds, selected, train, steps)
        shrink_without_evidence(base, added, fitting)
    final_test = test.log_likelihood(base)
    structure = _structure(scene, test, rays, base, azimuth, seed)
    result = Diagnosis(
        rounds=all_rounds,
        selected=selected,
        nll_before=nll_before,
        nll_after=float(-final_test.mean()),
        evidence=evidence,
        summary="",
        parameters={f"{e.name}.{key}": np.asarray(e.params[key]) for e in added for key in e.fitted_names()},
        structure=structure,
        model=base,
    )
    result.summary = verdict(result)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        text = json.dumps(result.to_json(), indent=1, default=float).encode()
        atomic_write(out / "diagnosis.json", lambda stream: stream.write(text))
        markdown = diagnosis_markdown(result) + intensity_section(
            intensity_residuals(log, scene, base, test_index), out
        )
        atomic_write(out / "diagnosis.md", lambda stream: stream.write(markdown.encode()))
        html = markdown_to_html(markdown, "mi-lidar diagnosis").encode()
        atomic_write(out / "diagnosis.html", lambda stream: stream.write(html))
        plot_structure(structure, out / "residual_structure.png")
    return result


def _drop_passengers(base, added, test, rounds, selected, train, steps):
    """Remove the selected effects that no longer win held out once every effect is refitted together.

    An effect chosen to mop up what an earlier one had not yet fitted loses its gain in the final
    joint refit; each later effect is dropped when the final model without it is not significantly
    worse held out (the same test as for joining). ``selected`` and the rows' status are updated.

    Returns:
        The model and its remaining added effects (refitted when one was dropped).
    """
    full = test.log_likelihood(base)
    kept = list(added)
    for effect in added[1:]:
        without = dataclasses.replace(base, effects=[e for e in base.effects if e is not effect])
        gain, p = held_out_test(full, test.log_likelihood(without))
        if p < P_VALUE and gain >= MIN_GAIN:
            continue
        i = added.index(effect)
        row = next(c for c in rounds[i] if c.name == selected[i])
        row.status = "dropped after the final refit"
        base, full = without, test.log_likelihood(without)
        kept.remove(effect)
    for name in [c.name for r in rounds for c in r if c.status == "dropped after the final refit"]:
        selected.remove(name)
    if len(kept) < len(added):
        fit_parts(base, train, steps=steps)
    return base, kept


def _structure(scene, test: Problem, rays: LogRays, model: SensorModel, azimuth: np.ndarray, seed: int) -> list:
    """Residual structure of ``model`` on the held-out rays (:func:`~mi_lidar.loop.residuals.residual_structure`)."""
    index = test.index
    first = first_elements(scene, test.table, test, model)
    sim_range, sim_hit = simulate_log_rays(scene, test.table, rays, model, seed + 7, index)
    dimensions = {
        "time": rays.time[index],
        "azimuth": azimuth,
        "beam": rays.beam[index],
        "range": first["nominal"],
        "label": np.where(first["label"] >= 0, first["label"], np.nan),
    }
    return residual_structure(dimensions, first["nominal"], rays.measured[index], rays.hit[index], sim_range, sim_hit)


def _values(values) -> str:
    return np.array2string(np.asarray(values), precision=4, threshold=6)


def verdict(d: Diagnosis) -> str:
    """The diagnosis in plain words; it names exactly the rows the tables mark ``joined``."""
    parts = []
    lost = [c for r in d.rounds for c in r if c.status == "lost in the joint refit"]
    if not d.selected:
        best = d.rounds[0][0] if d.rounds and d.rounds[0] else None
        parts.append("No missing catalog effect found: no candidate improves the model significantly held out.")
        if best is not None and not best.significant:
            parts.append(
                f"The best candidate, {best.name}, gains {best.test_gain:+.4f} nats/ray held out "
                f"(p = {best.p_value:.2g})."
            )
    for name in d.selected:
        c = next(c for r in d.rounds for c in r if c.name == name and c.status == "joined")
        mine = name.split("(")[0]
        params = ", ".join(
            f"{key.split('.', 1)[1]}={_values(v)}" for key, v in d.parameters.items() if key.split(".")[0] == mine
        )
        text = (
            f"The model is missing **{name}** ({params}): held-out NLL falls by {c.test_gain:.4f} nats/ray "
            f"{'' if math.isnan(c.test_gain_pct) else f'({c.test_gain_pct:.1f} %) '}"
            f"(held-out p = {c.p_value:.2g}; {c.k} parameter(s))."
        )
        groups = next((e["groups"] for e in d.evidence if e["effect"] == name), [])
        if groups:
            g = groups[0]
            text += (
                f" Its signature shows by {g['breakdown']}: in {g['group']} the NLL falls from "
                f"{g['nll_before']:.3f} to {g['nll_after']:.3f} nats/ray."
            )
        parts.append(text)
    dropped = [c.name for r in d.rounds for c in r if c.status == "dropped after the final refit"]
    if dropped:
        parts.append(
            "Joined, then dropped (no held-out gain once every effect was refitted together): "
            + ", ".join(dropped)
            + "."
        )
    if lost:
        parts.append(
            "Significant alone but not once refitted with the model's effects (not added): "
            + ", ".join(sorted({c.name for c in lost}))
            + "."
        )
    parts.append(f"Held-out NLL: {d.nll_before:.4f} -> {d.nll_after:.4f} nats/ray.")
    left = structure_verdict(d.structure)
    if left:
        parts.append(left + " See residual_structure.png.")
    return " ".join(parts)


def diagnosis_markdown(d: Diagnosis) -> str:
    """The diagnosis as a Markdown report: verdict, each round's ranking, evidence and residual structure."""
    lines = ["# Diagnosis", "", d.summary, ""]
    for i, ranked in enumerate(d.rounds):
        lines += [
            f"## Round {i + 1}",
            "",
            "| rank | candidate | k | held-out gain (nats/ray) | gain % | held-out p | significant | status "
            "| train LR |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for j, c in enumerate(ranked):
            pct = "-" if math.isnan(c.test_gain_pct) else f"{c.test_gain_pct:+.2f}"
            lines.append(
                f"| {j + 1} | {c.name} | {c.k} | {c.test_gain:+.4f} | {pct} | {c.p_value:.2g} | "
                f"{'yes' if c.significant else 'no'} | {c.status or '-'} | {c.lr:.1f} |"
            )
        lines.append("")
    for ev in d.evidence:
        lines += [
            f"### Where {ev['effect']} shows",
            "",
            "| breakdown | group | rays | NLL before | NLL after |",
            "|---|---|---|---|---|",
        ]
        lines += [
            f"| {g['breakdown']} | {g['group']} | {g['rays']} | {g['nll_before']:.3f} | {g['nll_after']:.3f} |"
            for g in ev["groups"]
        ]
        lines.append("")
    if d.structure:
        lines += [
            "## Residual structure of the final model",
            "",
            "![residual structure](residual_structure.png)",
            "",
            "| dimension | channel | chi2 | dof | p | largest departure | flagged |",
            "|---|---|---|---|---|---|---|",
        ]
        for st in d.structure:
            unit = "m" if st.channel == "range" else ""
            lines.append(
                f"| {st.dimension} | {st.channel} | {st.chi2:.1f} | {st.dof} | {st.p_value:.2g} | "
                f"{st.departure:.4f} {unit} | {'yes' if st.flagged else 'no'} |"
            )
        lines.append("")
    return "\n".join(lines)
