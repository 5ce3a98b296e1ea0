"""Outputs of the planar benchmark: ``benchmark.json``, PNG figures and one self-contained ``benchmark.html``.

Figures: the test NLL of every model; the residual ``z - r`` (measured range minus nominal range) of
the test beams beside that of each model's sampled scan; the test NLL by nominal-range bin. The files
are written into a staging folder inside the report folder, then moved in one after the other, so
that a run that fails or is stopped while writing leaves the previous report whole.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mi_lidar.core.atomic import atomic_path, atomic_write_text, staged_files  # noqa: E402
from mi_lidar.core.decimals import fixed  # noqa: E402
from mi_lidar.core.strict_json import write_json  # noqa: E402
from mi_lidar.io.markdown import plain  # noqa: E402
from mi_lidar.planar.benchmark import SAMPLED_SCANS  # noqa: E402

BINS = np.linspace(-1.5, 1.5, 121)
END_BINS = f"z - r (m; beyond \u00b1{BINS[-1]:g} m in the end bins)"  # the residual panels clip into their end bins


def _save(figure, path: Path) -> Path:
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(figure)
    return path


def nll_figure(result, path: Path) -> Path:
    """Bar chart: test NLL per model (nats per beam), bars from 0 (the score of a beam predicted with certainty:
    scores are probabilities of 1 cm bins, so no NLL is below it), so that their heights compare."""
    names = [r.name for r in result.rows]
    values = [r.test_nll for r in result.rows]
    figure, axis = plt.subplots(figsize=(7.5, 3.2))
    colors = ["tab:red" if n == "mi-lidar" else "tab:gray" for n in names]
    axis.bar(names, values, color=colors)
    for i, v in enumerate(values):
        axis.text(i, v, f"{v:.3f}", ha="center", va="bottom", fontsize=8)
    axis.set_ylabel("test NLL (nats/beam)")
    axis.set_title(f"{Path(result.source).name}: test NLL per model (lower is better)")
    axis.set_ylim(0.0, max(values) * 1.1)
    return _save(figure, path)


def residual_figure(result, path: Path) -> Path:
    """Histograms of ``z - r`` on the test beams: measured, and each model's sampled scan (M0, M1, M3b, NP-Reg
    and mi-lidar, those of them that were run; else every model run). Residuals beyond the bins' range are
    counted in the end bins, and the axis label says so (they are the log's short and long returns, not a peak)."""
    test = result.data.test
    both = test.hit & np.isfinite(test.nominal)
    measured = (test.z - test.nominal)[both]
    shown = [r for r in result.rows if r.name in ("M0", "M1", "M3b", "NP-Reg", "mi-lidar")] or result.rows
    figure, axes = plt.subplots(1, len(shown), figsize=(3.0 * len(shown), 2.8), sharey=True, squeeze=False)
    for axis, row in zip(axes[0], shown):
        z, hit = row.sampled
        sampled = (z - test.nominal)[hit & np.isfinite(test.nominal)]
        axis.hist(
            np.clip(measured, BINS[0], BINS[-1]),
            bins=BINS,
            density=bool(measured.size),  # no returns: an empty histogram, not 0/0
            histtype="stepfilled",
            alpha=0.4,
            color="black",
            label="measured",
        )
        axis.hist(
            np.clip(sampled, BINS[0], BINS[-1]),
            bins=BINS,
            density=bool(sampled.size),
            histtype="step",
            color="tab:red",
            label="sampled",
        )
        axis.set_yscale("log")
        axis.set_title(f"{row.name}: median |err| {row.samples['range_error_median']:.3f} m", fontsize=9)
        axis.set_xlabel(END_BINS, fontsize=8)
    axes[0][0].legend(fontsize=8)
    axes[0][0].set_ylabel("density (1/m)")
    return _save(figure, path)


def range_figure(result, path: Path) -> Path:
    """Test NLL per nominal-range bin, one line per model."""
    test = result.data.test
    edges = np.array([0, 1, 2, 3, 5, 8, 12, 20, 40, np.inf])
    r = np.where(np.isfinite(test.nominal), test.nominal, np.inf)
    which = np.clip(np.searchsorted(edges, r, side="right") - 1, 0, len(edges) - 2)
    labels = [f"{edges[i]:g}-{edges[i + 1]:g}" if np.isfinite(edges[i + 1]) else "miss" for i in range(len(edges) - 1)]
    figure, axis = plt.subplots(figsize=(7.5, 3.2))
    for row in result.rows:
        values = [float(-row.ll[which == i].mean()) if np.any(which == i) else np.nan for i in range(len(labels))]
        axis.plot(labels, values, marker="o", label=row.name, linewidth=2.0 if row.name == "mi-lidar" else 1.0)
    axis.set_xlabel("nominal range bin (m)")
    axis.set_ylabel("test NLL (nats/beam)")
    axis.legend(fontsize=7, ncol=3)
    return _save(figure, path)


REFERENCE = "sensor, re-paired"  # the reference row's name (:mod:`mi_lidar.planar.reference`)


def _sample_cells(s: dict) -> tuple[str, ...]:
    return (
        fixed(s["range_error_median"]),
        fixed(s["range_error_p90"]),
        fixed(s["f1"]),
        f"{fixed(s['histogram_l1'])} / {fixed(s['histogram_l1_draws'])} ± {fixed(s['histogram_l1_draws_se'])}",
        f"{fixed(s['crps_mean'])} ± {fixed(s['crps_mean_se'])} / {fixed(s['crps_median'], 4)}",
    )


def _table(rows: list, reference: dict) -> str:
    head = (
        "model",
        "test NLL",
        "train NLL",
        "NLL hits / misses",
        "miss F1 @0.5",
        "miss F1 (tuned thr.)",
        "sample median |err| (m)",
        "sample p90 |err| (m)",
        "sample hit/miss F1",
        "histogram L1 (m): one scan / mean of all sampled ± its standard error over them",
        "CRPS mean ± its standard error over the sampled scans / median (m)",
    )
    lines = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    body = [
        (
            r.name,
            f"{r.test_nll:.3f}",
            f"{r.train_nll:.3f}",
            f"{r.nll_hits:.2f} / {r.nll_misses:.2f}",
            f"{r.miss_at_half['f1']:.3f}",
            f"{r.miss_tuned['f1']:.3f} (thr {r.threshold:.2f})",
            *_sample_cells(r.samples),
        )
        for r in rows
    ]
    if reference:
        body.append((f"{REFERENCE} (reference)", "-", "-", "-", "-", "-", *_sample_cells(reference)))
    for cells in body:
        lines.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(lines + ["</table>"])


def _shared_errors(settings: dict) -> str:
    """A paragraph on how much neighbouring beams share their errors, real against mi-lidar's samples."""
    lags = settings.get("shared_errors_pit_lags")
    if not lags:
        return ""

    def row(values) -> str:
        return ", ".join(fixed(v, 2) for v in values)

    c = settings["beam_correlation"]
    return (
        f"<p>Shared errors of neighbouring beams (training scans; correlation of the normal scores of each "
        f"beam's PIT under mi-lidar's own samples, at lags {', '.join(str(k) for k in lags['lags'])} beams): "
        f"real {row(lags['real'])}; mi-lidar's samples {row(lags['sampled'])} (shared share "
        f"{c['shared']:.3f}, decay {c['rho']:.3f} per beam); with independent beams "
        f"{row(lags['uncorrelated'])}. The likelihood scores beams one by one and does not see this; "
        f"line fitting and scan matching do.</p>"
    )


def write_benchmark(result, out: Path) -> dict[str, Path]:
    """Write the JSON, the figures and the HTML page of ``result`` into ``out`` (see the module docstring).

    Raises:
        OSError: a failed write (a full disk, ``ulimit -f``), naming the file in ``out``; ``out`` keeps what it held.
    """
    with staged_files(out) as staging:
        files = _write_report(result, staging)
    return {key: out / path.name for key, path in files.items()}


def _write_report(result, out: Path) -> dict[str, Path]:
    files = {
        "json": write_json(out / "benchmark.json", result.to_json(), default=float),
        "nll": nll_figure(result, out / "nll.png"),
        "residuals": residual_figure(result, out / "residuals.png"),
        "ranges": range_figure(result, out / "nll_by_range.png"),
    }
    images = "".join(
        f'<p><img alt="{k}" src="data:image/png;base64,{base64.b64encode(files[k].read_bytes()).decode()}"/></p>'
        for k in ("nll", "residuals", "ranges")
    )
    info = result.to_json()
    chosen = "".join(f"<li>{html.escape(name)}: {html.escape(plain(v))}</li>" for name, v in info["settings"].items())
    nominal = info["nominal"]
    every = info["train_beams_in_log"]
    thinned = f" (of the log's {every:,}: evenly spaced scans)" if info["train_beams"] < every else ""
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>planar benchmark</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px;text-align:right}}th{{background:#eee}}</style></head><body>
<h1>Planar benchmark: {html.escape(Path(result.source).name or "log")}</h1>
<p>{info["scans"]} scans x {info["beams"]} beams; sensor no-return value {info["max_range_m"]:g} m;
{info["test_beams"]:,} test beams, {info["train_beams"]:,} training beams{thinned}; protocol
<code>docs/benchmark_planar.md</code> in mi-lidar (cell {result.data.protocol.cell} m, occ3 map, leave-out
{result.data.protocol.radius} m / {result.data.protocol.window} s, scores in 1 cm bins with the 1e-9 floor).</p>
<p>Nominal ray cast on test beams: median |z - r| {nominal["median_abs_err"]:.3f} m,
p90 {nominal["p90_abs_err"]:.3f} m; short (z &lt; r - 0.5 m) {nominal["short"]:.3f},
long {nominal["long"]:.3f}, measured misses {nominal["measured_miss"]:.3f},
nominal misses {nominal["nominal_miss"]:.3f} (of which returned: {nominal["unmapped_returns"]:.3f}),
incidence known for {nominal["incidence_known"]:.2f} of
nominal hits by the protocol's rule, for {nominal["surface_incidence_known"]:.2f} of the occupied
cells the test beams met by the surface rule (mi-lidar's).</p>
{"".join(f'<p style="color:#a40"><b>Warning:</b> {html.escape(w)}</p>' for w in info["warnings"])}
{_table(result.rows, result.reference)}
<p>Sample metrics compare one scan sampled from each model with the measured scan, beam by beam: a model
that reproduces the log's share of short and long returns (people, glass, doors) draws them at other
beams than the measurement, which raises the p90 error and lowers the hit/miss F1 even as its range
distribution (histogram L1) gets closer to the sensor's. The last row shows it: the measured test scans
re-paired, every beam given the measured outcome of a beam of another test scan with about the same
nominal range (its residual moved to this beam's nominal range): the sensor's own law given the nominal
range, sampled at other beams. It is a reference, not a model (it reads the test scans), and what a
model that samples like the sensor scores on the one-draw figures. The CRPS (continuous ranked probability score,
fair estimator from {SAMPLED_SCANS} sampled scans per model, a no-return counted as
{info["crps_no_return_m"]:g} m on both sides) is paired too, but proper: its expectation is lowest
for the sensor's own distribution, and for a model that never varies it is the plain |error|.</p>
{_shared_errors(info["settings"].get("mi-lidar", {}))}
{images}
<p>Chosen on the training scans:</p><ul>{chosen}</ul>
<p>Seconds: {html.escape(plain({k: round(v, 1) for k, v in result.seconds.items()}))}</p>
</body></html>"""
    files["html"] = atomic_write_text(out / "benchmark.html", page)
    return files
