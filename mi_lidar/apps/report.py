"""Outputs of ``evaluate-apps``: ``apps.json`` (every number), PNG figures and one self-contained ``apps.html``.

The page opens with the risk table (application x simulator, with standard errors over the draws) and
the paired differences of the simulators' risks. Per application: the loss ``l(alpha)`` at every prior
draw for each simulator (thesis fig. 3.16), the simulated against the real objective at the draws (bars:
the standard error over the runs), the development paths (thesis figs. 2.11, 3.17): the objective a
developer sees on each simulator along its path beside the real objective of the same settings, and a
sweep of one parameter at the best real setting with the loss and the application's effort metric along
it (thesis fig. 3.20). A
figure of one test scan, real and as each simulator samples it, shows what the applications see.
Files are written atomically.
"""

from __future__ import annotations

import base64
import html
import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from mi_lidar.apps.risk import WITHIN, AppResult, alpha_key, standard_error  # noqa: E402
from mi_lidar.core.atomic import atomic_write_text  # noqa: E402
from mi_lidar.core.strict_json import dumps, write_json  # noqa: E402
from mi_lidar.loop.report import save_figure  # noqa: E402

SAMPLE_KEYS = ("range_error_median", "range_error_p90", "f1", "histogram_l1")  # benchmark columns shown


def _colors(names) -> dict[str, str]:
    """One colour per source: the real scans black, mi-lidar red, the others from the default cycle."""
    others = iter(("C0", "C2", "C1", "C4", "C5", "C6", "C7", "C8", "C9"))
    return {n: "black" if n == "real" else "C3" if n == "mi-lidar" else next(others) for n in names}


def _save(figure, path: Path) -> Path:
    figure.tight_layout()
    return save_figure(figure, path)


def loss_figure(result: AppResult, path: Path, risk_se: dict[str, float] | None = None) -> Path:
    """``l(alpha_k)`` per simulator at the prior draws (sorted by real J), and simulated vs real J.

    ``risk_se``: the risk's standard error per simulator shown in the legend, when the report's table
    gives another one than ``result.risk_se`` (over the draws), e.g. a bootstrap over the starts.
    """
    risk_se = result.risk_se if risk_se is None else risk_se
    order = np.argsort(result.J["real"])
    colors = _colors(result.risk)
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 3.4))
    real_se = _run_errors(result, "real")
    for name in result.risk:
        style = {"linewidth": 2.2 if name == "mi-lidar" else 1.0, "color": colors[name], "marker": "o", "markersize": 3}
        label = f"{name} (risk {result.risk[name]:.3g} ± {risk_se.get(name, 0.0):.2g})"
        left.plot(result.loss(name)[order], label=label, **style)
        right.errorbar(
            result.J["real"],
            result.J[name],
            xerr=real_se,
            yerr=_run_errors(result, name),
            fmt="o",
            markersize=3,
            color=colors[name],
            label=name,
        )
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


def sweep_figure(result: AppResult, path: Path) -> Path:
    """Every source's J along the swept parameter (others at the best real setting), the loss, and the effort metric."""
    sweep = result.sweep
    values, metrics, effort = np.asarray(sweep["values"]), sweep["metrics"], sweep.get("effort")
    colors = _colors(metrics)
    panels = 3 if effort else 2
    figure, axes = plt.subplots(1, panels, figsize=(4.2 * panels, 3.4))
    for name, rows in metrics.items():
        style = {
            "color": colors[name],
            "marker": "o",
            "markersize": 3,
            "linewidth": 2.2 if name in ("real", "mi-lidar") else 1.0,
        }
        J = np.array([row["J"] for row in rows])
        axes[0].errorbar(
            values, J, yerr=[standard_error(row.get("J_runs", [row["J"]])) for row in rows], label=name, **style
        )
        if name != "real":
            real = np.array([row["J"] for row in metrics["real"]])
            axes[1].plot(values, np.abs(J - real), label=name, **style)
        if effort:
            axes[2].plot(values, [row[effort] for row in rows], label=name, **style)
    titles = (result.objective, "loss l = |J real - J sim|", effort or "")
    for axis, title in zip(axes, titles):
        axis.set_xlabel(sweep["parameter"])
        axis.set_title(title, fontsize=9)
        if values.min() > 0 and values.max() / values.min() > 20:
            axis.set_xscale("log")
    axes[0].legend(fontsize=7)
    figure.suptitle(f"{result.name}: along {sweep['parameter']} at {alpha_key(sweep['at'])}", fontsize=9)
    return _save(figure, path)


def _run_errors(result: AppResult, source: str) -> np.ndarray:
    """(M,) standard error over the runs of ``J`` at each draw (0 where the application reports no runs)."""
    rows = result.metrics.get(source, [])
    return np.array([standard_error(row.get("J_runs", [row["J"]])) for row in rows]) if rows else 0.0


def scan_figure(states, ranges: dict, t: int, path: Path) -> Path:
    """One test state seen by every source: its first scan's points (laser frame) and the map's visible wall pieces."""
    from mi_lidar.apps.lines import LineDetection
    from mi_lidar.apps.scans import run_ranges, scan_points

    names = list(ranges)
    colors = _colors(names)
    walls = LineDetection().walls(states, t)
    figure, axes = plt.subplots(1, len(names), figsize=(3.4 * len(names), 3.8), squeeze=False)
    shown = scan_points(run_ranges(ranges[names[0]], 1)[0, t], states.angles)  # every panel shows the first's extent
    lo, hi = (shown.min(axis=0) - 0.5, shown.max(axis=0) + 0.5) if len(shown) else (np.full(2, -1.0), np.ones(2))
    for axis, name in zip(axes[0], names):
        for x0, y0, x1, y1 in walls:
            axis.plot([x0, x1], [y0, y1], color="0.75", linewidth=3.0, solid_capstyle="butt")
        points = scan_points(run_ranges(ranges[name], 1)[0, t], states.angles)
        axis.scatter(points[:, 0], points[:, 1], s=2.0, color=colors[name], zorder=3)
        axis.set_title(name, fontsize=9)
        axis.set_xlim(lo[0], hi[0])
        axis.set_ylim(lo[1], hi[1])
        axis.set_aspect("equal", adjustable="box")
        axis.set_xlabel("x (m)")
    axes[0][0].set_ylabel("y (m)")
    figure.suptitle(f"state {t}: the scan's points in the laser frame; grey: the map's wall pieces it sees", fontsize=9)
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
        axis.set_xlim(-0.4, max(len(sim) - 1, 1) + 0.4)  # a path of one step: integer ticks, not +-0.05
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axes[0][0].set_ylabel(textwrap.fill(result.objective, 45), fontsize=8)
    axes[0][-1].legend(fontsize=7)
    return _save(figure, path)


def _risk_table(results: list[AppResult], simulators: tuple[str, ...]) -> str:
    head = ["application", *simulators]
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in results:
        best = min(r.risk.values())
        cells = [f"<td>{html.escape(r.name)}</td>"]
        for s in simulators:
            text = f"{r.risk[s]:.4g} ± {r.risk_se.get(s, 0.0):.2g}"
            cells.append(f"<td><b>{text}</b></td>" if r.risk[s] == best else f"<td>{text}</td>")
        lines.append("<tr>" + "".join(cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def _paired_table(results: list[AppResult], simulators: tuple[str, ...], focus: str = "mi-lidar") -> str:
    """Risk of ``focus`` minus each other simulator's at the same draws, with its standard error (negative: lower)."""
    others = [s for s in simulators if s != focus]
    if focus not in simulators or not others:
        return ""
    head = ["application", *(f"{focus} − {s}" for s in others)]
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in results:
        cells = [f"<td>{html.escape(r.name)}</td>"]
        for s in others:
            mean, se = r.paired[focus][s]
            cells.append(f"<td>{mean:+.4g} ± {se:.2g}{' *' if abs(mean) > 2 * se else ''}</td>")
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


def _scans_table(scans: dict) -> str:
    head = (
        "source",
        "no return",
        "short > 0.5 m",
        "long > 0.5 m",
        "median |z - nominal| (m)",
        "neighbour difference (m)",
        "outlier run (beams)",
    )
    keys = ("no_return", "short", "long", "median_abs_error", "neighbour_difference", "outlier_run")
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for name, row in scans.items():
        cells = (name, *(f"{row[k]:.3f}" for k in keys))
        lines.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def grids_text(parameters: list[dict]) -> str:
    """The parameters' prior grids as a person reads them: ``iterations in [5, 10, 20, 40], voxel in [0.1, 0.2] m``."""
    return ", ".join(
        f"{p['name']} in [{', '.join(f'{value:g}' for value in p['values'])}] {p['unit']}".strip() for p in parameters
    )


def _image(file: Path) -> str:
    return f'<p><img alt="{file.stem}" src="data:image/png;base64,{base64.b64encode(file.read_bytes()).decode()}"/></p>'


def write_report(evaluation, out: Path) -> dict[str, Path]:
    """Write the JSON, the figures and the HTML page of an :class:`~mi_lidar.apps.evaluate.AppsEvaluation`."""
    out.mkdir(parents=True, exist_ok=True)
    info = evaluation.to_json()
    files = {"json": write_json(out / "apps.json", info, default=float)}
    sections = []
    for r in evaluation.results:
        files[f"{r.name}_loss"] = loss_figure(r, out / f"{r.name}_loss.png")
        files[f"{r.name}_paths"] = path_figure(r, out / f"{r.name}_paths.png")
        swept = ""
        if r.sweep:
            files[f"{r.name}_sweep"] = sweep_figure(r, out / f"{r.name}_sweep.png")
            swept = _image(files[f"{r.name}_sweep"])
        params = grids_text(r.parameters)
        noise = ", ".join(f"{name} {value:.2g}" for name, value in r.run_se.items())
        sections.append(
            f"<h2>{html.escape(r.name)}</h2><p>J: {html.escape(r.objective)}. Parameters (uniform prior over "
            f"each grid): {html.escape(params)}. Best real J found: {r.best_real[0]:.4g} at "
            f"<code>{html.escape(alpha_key(r.best_real[1]))}</code>. Standard error of J over its runs (mean over "
            f"the draws): {html.escape(noise)}.</p>"
            f"{_pick_table(r)}{_image(files[f'{r.name}_loss'])}{_image(files[f'{r.name}_paths'])}{swept}"
        )
    scan_section = ""
    if evaluation.ranges is not None and evaluation.states.test.any():
        test = np.flatnonzero(evaluation.states.test)
        t = int(test[len(test) // 2])
        files["scan"] = scan_figure(evaluation.states, evaluation.ranges, t, out / "scan.png")
        scan_section = f"<h2>One test scan as each source gives it</h2>{_image(files['scan'])}"
    runs = info["runs"]
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>applications</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}}table{{border-collapse:collapse;margin:0.5em 0}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px;text-align:right}}th{{background:#eee}}</style></head><body>
<h1>Applications on real and simulated scans: {html.escape(Path(evaluation.source).name)}</h1>
<p>{info["states"]} states (every scan of the log; {info["test_states"]} of them the protocol's test scans) x
{info["beams"]} beams. Each simulator was fitted on the training scans of the real-planar protocol and sampled
{runs} scans per state at the same beams, in the same leave-out maps; real and simulated datasets differ only in the
sensor model. The trackers (registration, localization) run along the whole log, {runs} runs per setting; run r
has the same odometry noise, initial pose and particle draws on every source (common random numbers) and sees a
simulator's r-th sampled scans; odometry noise: {html.escape(info["odometry_noise"])}. Line detection runs on the
test scans (held out of every fit) against the walls of the map. Risk = mean over the {info["draws"]} prior draws
of l(alpha) = |J(alpha, real) - J(alpha, simulated)| (lower is better) ± its standard error over the draws.</p>
<h2>Risk (application x simulator)</h2>{_risk_table(evaluation.results, evaluation.simulators)}
<p>Paired differences at the same draws (± standard error; * where larger than twice it):</p>
{_paired_table(evaluation.results, evaluation.simulators)}
<h2>The simulators (observation level, test scans)</h2>{_benchmark_table(evaluation.benchmark)}
<h2>What the scans contain (every state, against the nominal ray cast)</h2>
<p>Shares of beams; the neighbour difference is the median |e_b - e_b+1| of neighbouring beams that both return
within 0.5 m of their nominal range (e = z - nominal): how smooth a surface's points are; the outlier run is the mean
length of the runs of no-return, short and long beams.</p>{_scans_table(evaluation.scans)}
{scan_section}
{"".join(sections)}
<p>Seconds: {html.escape(dumps({k: round(v, 1) for k, v in evaluation.seconds.items()}))}</p>
</body></html>"""
    files["html"] = atomic_write_text(out / "apps.html", page)
    return files
