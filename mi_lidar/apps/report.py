"""Outputs of ``evaluate-apps``: ``apps.json`` (every number), PNG figures and one self-contained ``apps.html``.

Per application: the loss ``l(alpha)`` at every prior draw for each simulator (thesis fig. 3.16), the
simulated against the real objective at the draws, and the development paths (thesis figs. 2.11,
3.17): the objective a developer sees on each simulator along its path beside the real objective of
the same settings. Files are written atomically.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from mi_lidar.apps.risk import WITHIN, AppResult, alpha_key  # noqa: E402
from mi_lidar.core.atomic import atomic_path, atomic_write  # noqa: E402

SAMPLE_KEYS = ("range_error_median", "range_error_p90", "f1", "histogram_l1")  # benchmark columns shown


def _colors(names) -> dict[str, str]:
    """One colour per source: the real scans black, mi-lidar red, the others from the default cycle."""
    others = iter(("C0", "C2", "C1", "C4", "C5", "C6", "C7", "C8", "C9"))
    return {n: "black" if n == "real" else "C3" if n == "mi-lidar" else next(others) for n in names}


def _save(figure, path: Path) -> Path:
    figure.tight_layout()
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=90)
    plt.close(figure)
    return path


def loss_figure(result: AppResult, path: Path) -> Path:
    """``l(alpha_k)`` per simulator at the prior draws (sorted by real J), and simulated vs real J."""
    order = np.argsort(result.J["real"])
    colors = _colors(result.risk)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 3.4))
    for name in result.risk:
        style = {"linewidth": 2.2 if name == "mi-lidar" else 1.0, "color": colors[name], "marker": "o", "markersize": 3}
        left.plot(result.loss(name)[order], label=f"{name} (risk {result.risk[name]:.3g})", **style)
        right.scatter(result.J["real"], result.J[name], s=14, color=colors[name], label=name)
    left.set_xlabel("prior draw k (sorted by real J)")
    left.set_ylabel("l(alpha_k) = |J real - J sim|")
    left.set_title(f"{result.name}: application-level loss")
    left.xaxis.set_major_locator(MaxNLocator(integer=True))
    left.legend(fontsize=7)
    lo = float(np.nanmin([np.nanmin(v) for v in result.J.values()]))
    hi = float(np.nanmax([np.nanmax(v) for v in result.J.values()]))
    right.plot([lo, hi], [lo, hi], color="black", linewidth=0.8)
    right.set_xlabel("J on real scans")
    right.set_ylabel("J on simulated scans")
    right.set_title(result.objective, fontsize=9)
    return _save(figure, path)


def path_figure(result: AppResult, path: Path) -> Path:
    """One panel per source: J along the path developed on it, as seen there and on real scans."""
    names = list(result.paths)
    figure, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 3.0), sharey=True, squeeze=False)
    best = result.best_real[0]
    for axis, name in zip(axes[0], names):
        sim, real = result.path_J[name]
        steps = np.arange(len(sim))
        axis.plot(steps, real, color="tab:blue", marker="o", label="real J")
        if name != "real":
            axis.plot(steps, sim, color="tab:red", marker="s", linestyle="--", label="simulated J")
        axis.axhline(best, color="black", linestyle=":", linewidth=0.8, label="best real J")
        axis.axhspan(best, best + WITHIN * abs(best), color="tab:blue", alpha=0.1)
        axis.set_title(f"developed on {name}", fontsize=9)
        axis.set_xlabel("development step")
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes[0][0].set_ylabel(result.objective, fontsize=8)
    axes[0][-1].legend(fontsize=7)
    return _save(figure, path)


def _risk_table(results: list[AppResult], simulators: tuple[str, ...]) -> str:
    head = ["application", *simulators]
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in results:
        best = min(r.risk.values())
        cells = [f"<td>{html.escape(r.name)}</td>"]
        for s in simulators:
            value = r.risk[s]
            cells.append(f"<td>{'<b>' if value == best else ''}{value:.4g}{'</b>' if value == best else ''}</td>")
        lines.append("<tr>" + "".join(cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def _pick_table(result: AppResult) -> str:
    head = ("developed on", "picked setting", "simulated J", "real J", f"within {WITHIN:.0%} of best real J")
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for name, pick in result.picks.items():
        cells = (
            name,
            alpha_key(pick["alpha"]),
            f"{pick['sim_J']:.4g}",
            f"{pick['real_J']:.4g}",
            "yes" if pick["within"] else "no",
        )
        lines.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def _benchmark_table(rows: list[dict]) -> str:
    head = ("simulator", "test NLL", "sample median |err| (m)", "sample p90 |err| (m)", "sample F1", "hist L1 (m)")
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in rows:
        s = r["samples"]
        cells = (r["model"], f"{r['test_nll']:.3f}", *(f"{s[k]:.3f}" for k in SAMPLE_KEYS))
        lines.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def _image(file: Path) -> str:
    return f'<p><img alt="{file.stem}" src="data:image/png;base64,{base64.b64encode(file.read_bytes()).decode()}"/></p>'


def write_report(evaluation, out: Path) -> dict[str, Path]:
    """Write the JSON, the figures and the HTML page of an :class:`~mi_lidar.apps.evaluate.AppsEvaluation`."""
    out.mkdir(parents=True, exist_ok=True)
    info = evaluation.to_json()
    files = {
        "json": atomic_write(out / "apps.json", lambda f: f.write(json.dumps(info, indent=1, default=float).encode()))
    }
    sections = []
    for r in evaluation.results:
        files[f"{r.name}_loss"] = loss_figure(r, out / f"{r.name}_loss.png")
        files[f"{r.name}_paths"] = path_figure(r, out / f"{r.name}_paths.png")
        params = ", ".join(f"{p['name']} in {p['values']} {p['unit']}".strip() for p in r.parameters)
        sections.append(
            f"<h2>{html.escape(r.name)}</h2><p>J: {html.escape(r.objective)}. Parameters (uniform prior over "
            f"each grid): {html.escape(params)}. Best real J found: {r.best_real[0]:.4g} at "
            f"<code>{html.escape(alpha_key(r.best_real[1]))}</code>.</p>"
            f"{_pick_table(r)}{_image(files[f'{r.name}_loss'])}{_image(files[f'{r.name}_paths'])}"
        )
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>applications</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}}table{{border-collapse:collapse;margin:0.5em 0}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px;text-align:right}}th{{background:#eee}}</style></head><body>
<h1>Applications on real and simulated scans: {html.escape(Path(evaluation.source).name)}</h1>
<p>{info["states"]} test states x {info["beams"]} beams. Each simulator was fitted on the training scans of the
real-planar protocol and sampled one scan per test state at the same beams, in the same leave-out map; real
and simulated datasets differ only in the sensor model. Risk = mean over the prior draws of
l(alpha) = |J(alpha, real) - J(alpha, simulated)| (lower is better).</p>
<h2>Risk (application x simulator)</h2>{_risk_table(evaluation.results, evaluation.simulators)}
<h2>The simulators (observation level, test scans)</h2>{_benchmark_table(evaluation.benchmark)}
{"".join(sections)}
<p>Seconds: {html.escape(json.dumps({k: round(v, 1) for k, v in evaluation.seconds.items()}))}</p>
</body></html>"""
    files["html"] = atomic_write(out / "apps.html", lambda f: f.write(page.encode()))
    return files
