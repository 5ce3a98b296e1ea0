"""Outputs of ``evaluate-apps-3d``: ``apps3d.json`` (every number), PNG figures and one self-contained ``apps3d.html``.

The figures are those of the planar report (:mod:`mi_lidar.apps.report`: ``l(alpha)`` at the prior
draws, simulated against real ``J``, development paths), plus the scans themselves seen from above
(the real scan beside each simulator's), so that the risk can be read against what the scans look
like. Files are written atomically.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from mi_lidar.apps.matching3d import scan_cloud
from mi_lidar.apps.report import _colors, _image, _pick_table, _save, grids_text, loss_figure, path_figure
from mi_lidar.apps.risk import alpha_key
from mi_lidar.core.atomic import atomic_write_text
from mi_lidar.core.strict_json import write_json
from mi_lidar.io.markdown import plain

BENCHMARK_KEYS = (
    ("nll", "test NLL (nats/ray)", "{:.3f}"),
    ("range_error_median", "sample median |err| (m)", "{:.3f}"),
    ("range_error_p90", "sample p90 |err| (m)", "{:.2f}"),
    ("f1", "sample hit F1", "{:.3f}"),
    ("histogram_l1", "hist L1 (m)", "{:.3f}"),
    ("chamfer", "Chamfer (m)", "{:.3f}"),
)


def scans_figure(evaluation, ranges: dict, path: Path, extent: float = 30.0) -> Path:
    """Top view of the real scan and of each simulator's, within ``extent`` m of the sensor."""
    import matplotlib.pyplot as plt

    names = ["real", *evaluation.simulators]
    colors = _colors(names)
    columns = min(4, len(names))
    rows = -(-len(names) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.2 * rows), squeeze=False)
    center = evaluation.states.origins.mean(axis=0)
    for axis, name in zip(axes.ravel(), names):
        points = scan_cloud(evaluation.states, ranges[name]) - center
        near = np.abs(points[:, :2]).max(axis=1) < extent
        axis.scatter(points[near, 0], points[near, 1], s=0.2, color=colors[name], rasterized=True)
        axis.set_title(f"{name}: {int(near.sum()):,} points", fontsize=9)
        axis.set_aspect("equal")
        axis.set_xlim(-extent, extent)
        axis.set_ylim(-extent, extent)
    for axis in axes.ravel()[len(names) :]:
        axis.axis("off")
    figure.suptitle(f"Each source's scan of the test rays from above, within {extent:g} m of the sensor")
    figure.supxlabel("x from the sensor (m)")  # the panels had no axis labels
    figure.supylabel("y from the sensor (m)")
    return _save(figure, path)


def _risk_table(evaluation) -> str:
    head = ["application", *evaluation.simulators]
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for r in evaluation.results:
        se, best = evaluation.risk_se[r.name], min(r.risk.values())
        cells = [f"<td>{html.escape(r.name)}</td>"]
        for s in evaluation.simulators:
            text = f"{r.risk[s]:.4g} &plusmn; {se[s]:.2g}"
            cells.append(f"<td>{f'<b>{text}</b>' if r.risk[s] == best else text}</td>")
        lines.append("<tr>" + "".join(cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def _benchmark_table(rows: list[dict]) -> str:
    head = ["simulator", *(title for _, title, _ in BENCHMARK_KEYS)]
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for row in rows:
        cells = [row["model"], *(fmt.format(row[key]) for key, _, fmt in BENCHMARK_KEYS)]
        lines.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def write_report(evaluation, out: Path, ranges: dict | None = None) -> dict[str, Path]:
    """Write the JSON, the figures and the HTML page of a :class:`~mi_lidar.apps.evaluate3d.FrameEvaluation`.

    Args:
        evaluation: the evaluation.
        out: report folder.
        ranges: the scans ``{source: (1, N) ranges}`` for the top-view figure (read from
            ``out/cache/frame.npz`` when None).
    """
    out.mkdir(parents=True, exist_ok=True)
    info = evaluation.to_json()
    files = {"json": write_json(out / "apps3d.json", info, default=float)}
    if ranges is None:
        with np.load(out / "cache" / "frame.npz") as z:
            ranges = {str(name): z[f"ranges/{name}"] for name in z["sources"]}
    files["scans"] = scans_figure(evaluation, ranges, out / "scans.png")
    sections = []
    for r in evaluation.results:
        files[f"{r.name}_loss"] = loss_figure(r, out / f"{r.name}_loss.png", evaluation.risk_se[r.name])
        files[f"{r.name}_paths"] = path_figure(r, out / f"{r.name}_paths.png")
        params = grids_text(r.parameters)
        sections.append(
            f"<h2>{html.escape(r.name)}</h2><p>J: {html.escape(r.objective)}. Parameters (uniform prior over "
            f"each grid): {html.escape(params)}. Best real J found: {r.best_real[0]:.4g} at "
            f"<code>{html.escape(alpha_key(r.best_real[1]))}</code>.</p>"
            f"{_pick_table(r)}{_image(files[f'{r.name}_loss'])}{_image(files[f'{r.name}_paths'])}"
        )
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>3D applications</title>
<style>body{{font-family:sans-serif;max-width:1200px;margin:2em auto}}table{{border-collapse:collapse;margin:0.5em 0}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px;text-align:right}}th{{background:#eee}}</style></head><body>
<h1>3D applications on a real frame and simulated scans: {html.escape(Path(evaluation.source).name)}</h1>
<p>Scene: the mesh of the frame's columns 0 mod 4. Every simulator was fitted on the calibration columns
(2 mod 4) and sampled the test columns (odd) at the same rays; the real dataset is the measured test columns.
The map every scan is registered to is the measured calibration points ({info["map_points"]:,} points); each
registration starts from the same {info["starts"]} seeded initial-pose errors. Real and simulated datasets differ
only in the sensor model. Risk = mean over the prior draws of l(alpha) = |J(alpha, real) - J(alpha, simulated)|
(lower is better), &plusmn; its bootstrap standard error over the starts.</p>
<h2>Risk (application x simulator)</h2>{_risk_table(evaluation)}
<h2>The simulators (observation level, {info["test_rays"]:,} test rays)</h2>
<p>NLL of the measured scan beside the realism of the sampled scan: a simulator that wins the likelihood by
spreading its mass shows it here.</p>{_benchmark_table(evaluation.benchmark)}
<h2>The scans (top view, 30 m around the sensor)</h2>{_image(files["scans"])}
{"".join(sections)}
<p>Seconds: {html.escape(plain({k: round(v, 1) for k, v in evaluation.seconds.items()}))}</p>
</body></html>"""
    files["html"] = atomic_write_text(out / "apps3d.html", page)
    return files
