"""Which effect is missing? Fit every candidate on training rays, rank them on held-out rays.

For each catalog effect (and every user-registered effect) not yet in the model, and for each
choice of its first option, :func:`diagnose` adds the effect to the model, fits its parameters
on a training split (:func:`~mi_lidar.core.problem.fit_parts`) and scores held-out rays. A
candidate is **significant** when

* its training log-likelihood gain passes the likelihood-ratio test against the number ``k`` of
  parameters it adds (``LR = 2 dLL``, chi-square with ``k`` degrees of freedom, p < 0.001) *and*
  the Bayesian information criterion prefers it (``dBIC = k ln n - LR < 0``), and
* it lowers the held-out NLL.

Candidates are ranked by held-out NLL gain per ray. Selection is greedy: the best significant
effect joins the model, every effect of the augmented model is refitted jointly (an effect found
earlier may have absorbed part of the new one), and the remaining candidates are tried again
(``rounds`` times), so two hidden effects come out first and second. Scores are floored per ray
with the one floor of :func:`~mi_lidar.core.likelihood.score`, so one return the model cannot produce does not make a
held-out NLL infinite.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.core.problem import Problem, fit_parts, n_parameters
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.catalog import candidate, candidate_names, variants
from mi_lidar.loop.compare import BREAKDOWNS, RayTable, first_elements, group_keys

P_VALUE = 1e-3
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
        train_gain: training log-likelihood gain, nats (total).
        test_gain: held-out NLL decrease, nats per ray.
        test_gain_pct: the same relative to the model's held-out NLL, percent (NaN when that NLL
            is within 1 nat/ray of zero, see :func:`relative_gain`).
        lr: likelihood-ratio statistic ``2 train_gain``.
        p_value: chi-square(k) tail probability of ``lr``.
        delta_bic: ``k ln n - lr`` (negative favours the candidate).
        significant: passes both tests and lowers held-out NLL.
        parameters: fitted values.
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
        selected: names of the effects added, in order.
        nll_before, nll_after: held-out NLL per ray of the given and of the augmented model.
        evidence: per selected effect, the breakdown groups where its gain concentrates.
        summary: the plain-words verdict.
        model: the augmented, fitted model.
    """

    rounds: list
    selected: list
    nll_before: float
    nll_after: float
    evidence: list
    summary: str
    model: SensorModel = field(repr=False, default=None)

    def ranking(self) -> list[dict]:
        """The first round's ranking as JSON-able rows."""
        return [c.row() for c in self.rounds[0]] if self.rounds else []

    def to_json(self) -> dict:
        return {
            "selected": self.selected,
            "nll_before": self.nll_before,
            "nll_after": self.nll_after,
            "rounds": [[c.row() for c in r] for r in self.rounds],
            "evidence": self.evidence,
            "summary": self.summary,
        }


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
    steps: int = 120,
    rounds: int = 2,
    max_train: int = 200_000,
    max_test: int = 200_000,
    seed: int = 0,
    progress=None,
    force: bool = False,
) -> Diagnosis:
    """Rank the effects missing from ``model`` by their held-out gain on ``log``.

    Args:
        log: measured log.
        scene: loaded Mitsuba scene or scene XML path.
        model: the current sensor model (default: the scene's); its effects are refitted first.
        out: folder for ``diagnosis.json`` and ``diagnosis.md`` (nothing written when None).
        candidates: effect names to try (default: every registered effect not in the model).
        steps: Adam steps per fit.
        rounds: greedy selection rounds (effects added at most).
        max_train, max_test: rays per split (random subsample beyond).
        seed: subsampling seed.
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
    table = ElementTable.from_scene(scene)
    train = Problem.build(scene, rays, train_index, table)
    test = Problem.build(scene, rays, test_index, table)
    n_beams, n_labels = log.shape[1], int(np.asarray(train.table.label).max()) + 1
    if base.effects:
        fit_parts(base, train, steps=steps)
    first = first_elements(scene, test.table, test, base)
    azimuth = np.degrees(
        np.arctan2(
            *[
                log.directions[
                    0 if log.directions.shape[0] == 1 else rays.scan[test_index],
                    rays.beam[test_index],
                    rays.column[test_index],
                    i,
                ]
                for i in (1, 0)
            ]
        )
    )
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

    def score(m: SensorModel) -> tuple[float, float]:
        train.trace(m)
        test.trace(m)
        return float(train.log_likelihood(m).sum()), float(test.log_likelihood(m).sum())

    base_train, base_test = score(base)
    nll_before = -base_test / test_index.size
    all_rounds, selected, evidence = [], [], []
    names = [(n, v) for n in candidate_names(base.effects, candidates) for v in variants(n)]
    total = len(names) * rounds
    done = 0
    for _ in range(rounds):
        ranked = []
        for name, variant in names:
            effect = candidate(name, n_beams, n_labels, **variant)
            trial = dataclasses.replace(base, effects=base.effects + [effect])
            train.trace(trial)
            fit = fit_parts(trial, train, [effect], steps=steps)
            lltr, llte = score(trial)
            k = n_parameters([effect])
            gain_tr = lltr - base_train
            lr = max(2.0 * gain_tr, 0.0)
            p = float(stats.chi2.sf(lr, k))
            dbic = k * math.log(train_index.size) - lr
            gain_te = (llte - base_test) / test_index.size
            label = name + (f"({', '.join(f'{k}={v}' for k, v in variant.items())})" if variant else "")
            ranked.append(
                Candidate(
                    name=label,
                    k=k,
                    train_gain=gain_tr,
                    test_gain=gain_te,
                    test_gain_pct=relative_gain(gain_te, nll_before),
                    lr=lr,
                    p_value=p,
                    delta_bic=dbic,
                    significant=bool(p < P_VALUE and dbic < 0 and gain_te > 0),
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
        best = ranked[0] if ranked else None
        if best is None or not best.significant:
            break
        augmented = dataclasses.replace(base, effects=base.effects + [best.effect])
        fit_parts(augmented, train, steps=steps)  # joint refit: earlier effects adapt to the new one
        evidence.append({"effect": best.name, "groups": _evidence(test, base, augmented, table)})
        base = augmented
        selected.append(best.name)
        base_train, base_test = score(base)
        chosen = best.name.split("(")[0]
        names = [(n, v) for n, v in names if n != chosen]
        done = len(all_rounds) * len(names)
    result = Diagnosis(
        rounds=all_rounds,
        selected=selected,
        nll_before=nll_before,
        nll_after=-base_test / test_index.size,
        evidence=evidence,
        summary="",
        model=base,
    )
    result.summary = verdict(result)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "diagnosis.json").write_text(json.dumps(result.to_json(), indent=1, default=float))
        (out / "diagnosis.md").write_text(diagnosis_markdown(result))
    return result


def verdict(d: Diagnosis) -> str:
    """The diagnosis in plain words."""
    if not d.selected:
        best = d.rounds[0][0] if d.rounds and d.rounds[0] else None
        tail = (
            (
                f" The best candidate, {best.name}, gains {best.test_gain:+.4f} nats/ray held out "
                f"(p = {best.p_value:.2g}, dBIC = {best.delta_bic:+.1f})."
            )
            if best
            else ""
        )
        return f"No missing effect found: no candidate improves the model significantly.{tail}"
    parts = []
    for i, name in enumerate(d.selected):
        c = next(c for c in d.rounds[i] if c.name == name)
        params = ", ".join(
            f"{k.split('.', 1)[1]}={np.array2string(np.asarray(v), precision=4, threshold=6)}"
            for k, v in c.parameters.items()
        )
        text = (
            f"The model is missing **{name}** ({params}): held-out NLL falls by {c.test_gain:.4f} nats/ray "
            f"{'' if math.isnan(c.test_gain_pct) else f'({c.test_gain_pct:.1f} %)'}; "
            f"likelihood ratio {c.lr:.1f} for {c.k} parameter(s), "
            f"p = {c.p_value:.2g}, dBIC = {c.delta_bic:+.1f}."
        )
        groups = d.evidence[i]["groups"] if i < len(d.evidence) else []
        if groups:
            g = groups[0]
            text += (
                f" Its signature shows by {g['breakdown']}: in {g['group']} the NLL falls from "
                f"{g['nll_before']:.3f} to {g['nll_after']:.3f} nats/ray."
            )
        parts.append(text)
    parts.append(f"Held-out NLL: {d.nll_before:.4f} -> {d.nll_after:.4f} nats/ray.")
    return " ".join(parts)


def diagnosis_markdown(d: Diagnosis) -> str:
    """The diagnosis as a Markdown report: verdict, then each round's ranking."""
    lines = ["# Diagnosis", "", d.summary, ""]
    for i, ranked in enumerate(d.rounds):
        lines += [
            f"## Round {i + 1}",
            "",
            "| rank | candidate | k | held-out gain (nats/ray) | gain % | LR | p | dBIC | significant |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for j, c in enumerate(ranked):
            pct = "-" if math.isnan(c.test_gain_pct) else f"{c.test_gain_pct:+.2f}"
            lines.append(
                f"| {j + 1} | {c.name} | {c.k} | {c.test_gain:+.4f} | {pct} | {c.lr:.1f} | "
                f"{c.p_value:.2g} | {c.delta_bic:+.1f} | {'yes' if c.significant else 'no'} |"
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
    return "\n".join(lines)
