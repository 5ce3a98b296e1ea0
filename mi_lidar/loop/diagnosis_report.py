"""The diagnosis told: the verdict in plain words, the Markdown / HTML report, its JSON and figures.

:func:`write_report` writes into the report folder:

* ``diagnosis.md`` and ``diagnosis.html``: the verdict, each round's ranking (held-out gain, p-value,
  status), the held-out NLL beside the realism of samples for the given model, after each joined
  candidate and for the final model, where each joined candidate shows, and the residual structure
  left;
* ``before_after_<k>.png`` per joined candidate: held-out NLL, mean range residual and return rate
  (measured minus model) by nominal range, incidence and beam, before and after it joined;
* ``residual_structure.png`` (:func:`~mi_lidar.loop.residuals.plot_structure`) and ``diagnosis.json``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_write_text
from mi_lidar.core.strict_json import write_json
from mi_lidar.io.markdown import markdown_to_html, p_phrase, p_value, plain, words
from mi_lidar.loop.residuals import (
    MIN_GROUP,
    PARAGRAPH,
    UNITS,
    Structure,
    departure_text,
    group_index,
    plot_structure,
    residual_structure,
    structure_verdict,
)
from mi_lidar.loop.selection import DROPPED, JOINED, LOST, MIN_GAIN, REPLACED

FIGURE_DIMENSIONS = ("range", "incidence", "beam")
MIN_SHOWN = 30  # held-out rays a group needs to be drawn


def values_text(values) -> str:
    """A fitted parameter's values as text: one number, a short list, or the spread of many (per beam)."""
    a = np.asarray(values, dtype=np.float64).ravel()
    return plain(a[0] if a.size == 1 else a)


def verdict(d) -> str:
    """The diagnosis in plain words, a paragraph per finding; it names exactly the rows the tables mark ``joined``."""
    parts = []
    rows = [c for r in d.rounds for c in r]
    if not d.selected:
        best = d.rounds[0][0] if d.rounds and d.rounds[0] else None
        parts.append("No missing catalog effect found: no candidate improves the model significantly held out.")
        if best is not None and not best.significant:
            parts.append(
                f"The best candidate, {best.name}, gains {best.test_gain:+.4f} nats/ray held out "
                f"({p_phrase(best.p_value)})."
            )
    for name in d.selected:
        c = next(c for c in rows if c.name == name and c.status == JOINED)
        gain = f"held-out NLL falls by {c.test_gain:.4f} nats/ray " + (
            "" if math.isnan(c.test_gain_pct) else f"({c.test_gain_pct:.1f} %) "
        )
        if c.kind == "density":
            replaced = [r.name for r in rows if r.status == REPLACED]
            instead = f"the model with {', '.join(replaced)}" if replaced else "the given model"
            text = (
                f"No combination of catalog effects explains the log as well as a learned density: **{name}** "
                f"replaces the model's return density, {gain}against {instead} (held-out {p_phrase(c.p_value)}). "
                "It describes what the sensor does without saying why; a physical effect would say more (see "
                "docs/writing_an_effect.md)."
            )
        else:
            mine = name.split("(")[0]
            params = ", ".join(
                f"{key.split('.', 1)[1]}={values_text(v)}"
                for key, v in d.parameters.items()
                if key.split(".")[0] == mine
            )
            held = f"held-out {p_phrase(c.p_value)}; {c.k} parameter(s)"
            text = f"The model is missing **{name}** ({params}): {gain}({held})."
        groups = next((e["groups"] for e in d.evidence if e["effect"] == name), [])
        if groups:
            g = groups[0]
            text += (
                f" Its signature shows by {words(g['breakdown'])}: in {g['group']} the NLL falls from "
                f"{g['nll_before']:.3f} to {g['nll_after']:.3f} nats/ray."
            )
        parts.append(text)
    dropped = [c.name for c in rows if c.status == DROPPED]
    if dropped:
        parts.append(
            "Joined, then dropped (no held-out gain once every effect was refitted together): "
            + ", ".join(dropped)
            + "."
        )
    lost = sorted({c.name for c in rows if c.status == LOST})
    if lost:
        parts.append(
            "Significant alone but not once refitted with the model's effects (not added): " + ", ".join(lost) + "."
        )
    parts += [
        f"The fit of {f['candidate']} failed (round {f['round']}, {f['stage']}), so it was left out and not tested: "
        f"{f['reason']}."
        if f["round"] is not None
        else f"The {f['stage']} of {f['candidate']} failed, so {f['kept']} (the held-out figures are of those "
        f"values): {f['reason']}."
        for f in d.failed
    ]
    parts += [f"Warning: {w}" for w in d.warnings()]
    parts.append(f"Held-out NLL: {d.nll_before:.4f} -> {d.nll_after:.4f} nats/ray.")
    left = structure_verdict(d.structure)
    if left:
        if d.selected:
            left += (
                f" What was selected ({', '.join(d.selected)}) stands in for it in part: it lowers the held-out NLL "
                "but leaves this structure, so its fitted values describe an average, not the cause."
            )
        parts.append(left + " See residual_structure.png.")
    return PARAGRAPH.join(parts)


def _ranking(d) -> list[str]:
    lines = []
    for i, ranked in enumerate(d.rounds):
        learned = ranked and ranked[0].kind == "density"
        lines += [
            "## Learned densities against the model with the effects found" if learned else f"## Round {i + 1}",
            "",
            "| rank | candidate | k | held-out gain (nats/ray) | gain % | held-out p | significant | status "
            "| training LR statistic |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for j, c in enumerate(ranked):
            pct = "-" if math.isnan(c.test_gain_pct) else f"{c.test_gain_pct:+.2f}"
            lines.append(
                f"| {j + 1} | {c.name} | {c.k} | {c.test_gain:+.4f} | {pct} | {p_value(c.p_value)} | "
                f"{'yes' if c.significant else 'no'} | {c.status or '-'} | {c.lr:,.1f} |"
            )
        lines.append("")
    if d.rounds:
        lines += [
            "k: fitted parameters (one per beam or label for a per-beam or per-label effect); training LR statistic: "
            "twice the log-likelihood gain on the fitting rays (nats), reported, not used to rank.",
            "",
        ]
    if any(c.kind == "density" for r in d.rounds for c in r):
        lines += [
            "A learned density replaces the model with the effects found only when it beats it significantly held "
            f"out, by {MIN_GAIN} nats/ray at least: a physical effect says why, a learned density only what.",
            "",
        ]
    return lines


def _realism(d) -> list[str]:
    lines = [
        "## Likelihood beside the realism of samples (held-out rays, one sampled scan per model)",
        "",
        "| model | NLL (nats/ray) | median / p90 abs. range error (m) | return rate sampled / measured "
        "| hit/miss F1 | histogram distance (m) | samples |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in d.realism:
        m = r.metrics
        lines.append(
            f"| {r.model} | {m['nll']:.4f} | {m['range_error_median']:.4f} / {m['range_error_p90']:.4f} | "
            f"{m['hit_rate_simulated']:.3f} / {m['hit_rate_measured']:.3f} | {m['f1']:.3f} | "
            f"{m['histogram_l1']:.4f} | {'**clearly worse**' if r.warning else 'ok'} |"
        )
    return lines + [""]


def diagnosis_markdown(d) -> str:
    """The diagnosis as a Markdown report: verdict, rankings, realism, evidence and residual structure."""
    lines = ["# Diagnosis", "", d.summary, "", *_ranking(d), *_realism(d)]
    for k, ev in enumerate(d.evidence):
        lines += [
            f"### Where {ev['effect']} shows",
            "",
            f"![before and after {ev['effect']}](before_after_{k + 1}.png)",
            "",
            "| breakdown | group | rays | NLL before | NLL after |",
            "|---|---|---|---|---|",
        ]
        lines += [
            f"| {words(g['breakdown'])} | {g['group']} | {g['rays']:,} | {g['nll_before']:.3f} | {g['nll_after']:.3f} |"
            for g in ev["groups"]
        ]
        lines.append("")
    if d.structure:
        lines += [
            "## Residual structure of the final model",
            "",
            "![residual structure](residual_structure.png)",
            "",
            "| dimension | channel | chi2 | dof | p | RMS departure beyond noise | flagged |",
            "|---|---|---|---|---|---|---|",
        ]
        lines += [structure_row(st) for st in d.structure]
        lines.append("")
    return "\n".join(lines)


def structure_row(st: Structure) -> str:
    """One row of the report's residual-structure table.

    A dimension with fewer than two groups of :data:`~mi_lidar.loop.residuals.MIN_GROUP` rays (one label in
    the scene, one beam of a planar scanner) has nothing to compare: its row says so instead of chi2 0 for
    0 degrees of freedom.
    """
    if st.dof == 0:
        untestable = f"not testable (fewer than 2 groups of {MIN_GROUP} rays)"
        return f"| {st.dimension} | {st.channel} | - | - | - | - | {untestable} |"
    return (
        f"| {st.dimension} | {st.channel} | {st.chi2:.1f} | {st.dof} | {p_value(st.p_value)} | "
        f"{departure_text(st, 2)} | {'yes' if st.flagged else 'no'} |"
    )


def _beam_groups(beam: np.ndarray, groups: int = 12) -> np.ndarray:
    """Each ray's beam, or, for a scanner of more than 32 beams, the centre of its group of neighbouring beams.

    ``groups``: groups of neighbouring beams the scanner's beams fall into.

    A planar scanner's 360 beams leave a few held-out rays per beam, too few to plot (:data:`MIN_SHOWN`).
    """
    if np.unique(beam).size <= 32:
        return beam
    edges = np.linspace(beam.min(), beam.max() + 1.0, groups + 1)
    return (0.5 * (edges[:-1] + edges[1:]))[np.clip(np.searchsorted(edges, beam, side="right") - 1, 0, groups - 1)]


def plot_before_after(d, k: int, path: Path) -> Path:
    """Figure of joined candidate ``k`` (0-based): NLL, range residual and return rate by range, incidence, beam.

    The groups are those of the held-out rays' first element under the given model; residuals are
    measured minus sampled (:func:`~mi_lidar.loop.residuals.residual_structure`), before (grey) and
    after (colour) the candidate joined.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_lidar.loop.report import save_figure

    t = d.held_out
    before, after = (d.realism[i] for i in d.evidence[k]["realism"])
    values = {
        "range": t.nominal,
        "incidence": np.where(np.isfinite(t.nominal), np.degrees(np.arccos(np.clip(t.cos_incidence, 0, 1))), np.nan),
        "beam": _beam_groups(t.beam.astype(float)),
    }
    fig, axes = plt.subplots(3, len(FIGURE_DIMENSIONS), figsize=(4.2 * len(FIGURE_DIMENSIONS), 8.0), squeeze=False)
    for col, dimension in enumerate(FIGURE_DIMENSIONS):
        index, centers = group_index(dimension, values[dimension])
        for realism, colour, label in ((before, "0.55", "before"), (after, "tab:red", "after")):
            ok = index >= 0
            count = np.bincount(index[ok], minlength=centers.size)
            nll = -np.bincount(index[ok], weights=realism.ll[ok], minlength=centers.size) / np.maximum(count, 1)
            shown = count >= MIN_SHOWN
            axes[0, col].plot(centers[shown], nll[shown], "o-", color=colour, ms=3, label=label)
            found = residual_structure(
                {dimension: values[dimension]}, t.nominal, t.measured, t.hit, realism.sim_range, realism.sim_hit
            )
            for row, channel in ((1, "range"), (2, "returns")):
                s = next(s for s in found if s.channel == channel)
                axes[row, col].errorbar(
                    s.centers, 100 * s.difference, yerr=200 * s.error, fmt="o-", color=colour, ms=3, label=label
                )
        unit = UNITS[dimension]
        for row in range(3):
            axes[row, col].set_xlabel(f"{dimension} ({unit})" if unit else dimension)
            if row:  # at least +-1 cm / point, so that agreement looks flat
                axes[row, col].axhline(0.0, color="grey", lw=0.6)
                low, high = axes[row, col].get_ylim()
                axes[row, col].set_ylim(min(low, -1.0), max(high, 1.0))
        axes[0, col].legend(fontsize=7)
    axes[0, 0].set_ylabel("held-out NLL, nats/ray")
    axes[1, 0].set_ylabel("range residual, cm\n(measured - sampled)")
    axes[2, 0].set_ylabel("return rate, points\n(measured - sampled)")
    fig.suptitle(f"Before and after {d.evidence[k]['effect']} joined (held-out rays; bars: 2 standard errors)")
    fig.tight_layout()
    return save_figure(fig, path)


def write_report(d, out: Path, appendix: str = "") -> None:
    """Write ``diagnosis.json``, ``diagnosis.md``, ``diagnosis.html`` and the figures into ``out``.

    ``appendix``: Markdown sections added after the diagnosis (e.g. the intensity section).
    """
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "diagnosis.json", d.to_json(), default=float)
    markdown = diagnosis_markdown(d) + appendix
    atomic_write_text(out / "diagnosis.md", markdown)
    atomic_write_text(out / "diagnosis.html", markdown_to_html(markdown, "mi-lidar diagnosis"))
    plot_structure(d.structure, out / "residual_structure.png")
    for k in range(len(d.evidence)):
        plot_before_after(d, k, out / f"before_after_{k + 1}.png")
