"""Report writers of the loop: plots, residual range image, residual PLY, Markdown and HTML."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mi_lidar.core.atomic import atomic_path, atomic_write_text, output_folder  # noqa: E402
from mi_lidar.core.strict_json import write_json  # noqa: E402
from mi_lidar.io.markdown import effects_text, markdown_to_html, plain, table_cell, words  # noqa: E402
from mi_lidar.loop.compare import NO_ELEMENT_GROUP  # noqa: E402


def save_figure(fig, path: Path, dpi: int = 90) -> Path:
    """Write ``fig`` as a PNG at ``path`` atomically and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return Path(path)


PLOTTED = ("range", "incidence", "azimuth", "beam", "label", "time")
FMT = {
    "rays": "{:,d}",
    "nll": "{:.3f}",
    "nll_median": "{:.3f}",
    "hit_rate_measured": "{:.3f}",
    "hit_rate_simulated": "{:.3f}",
    "range_error_mean": "{:.4f}",
    "range_error_median": "{:.4f}",
    "precision": "{:.3f}",
    "recall": "{:.3f}",
    "f1": "{:.3f}",
    "histogram_l1": "{:.4f}",
    "excess_nll": "{:,.1f}",
    "residual_median": "{:+.4f}",
    "returns": "{:,d}",
    "intensity_measured": "{:.1f}",
    "intensity_expected": "{:.1f}",
    "intensity_ratio": "{:.2f}",
    "intensity_nll": "{:.3f}",
}
NAMES = {
    "rays": "rays",
    "nll": "NLL (nats/ray)",
    "nll_median": "median NLL",
    "hit_rate_measured": "hit rate (meas.)",
    "hit_rate_simulated": "hit rate (sim.)",
    "range_error_mean": "mean |range error| (m)",
    "range_error_median": "median |range error| (m)",
    "precision": "precision",
    "recall": "recall",
    "f1": "F1",
    "histogram_l1": "histogram L1 (m)",
    "excess_nll": "excess NLL (nats)",
    "residual_median": "median residual (m)",
    "returns": "returns",
    "intensity_measured": "median intensity (meas.)",
    "intensity_expected": "median intensity (model)",
    "intensity_ratio": "median (meas.+1)/(model+1)",
    "intensity_nll": "intensity NLL (nats/return)",
}


def fmt(key: str, value) -> str:
    """A metric formatted for a table."""
    if isinstance(value, float) and not np.isfinite(value):
        return "-"
    return FMT.get(key, "{}").format(value)


def markdown_table(rows: list[dict], keys: list[str]) -> str:
    """Rows of dicts as a Markdown table over ``keys`` (cells escaped by :func:`table_cell`)."""
    head = "| " + " | ".join(table_cell(NAMES.get(k, k)) for k in keys) + " |"
    rule = "|" + "---|" * len(keys)
    body = ["| " + " | ".join(table_cell(fmt(k, r[k])) for k in keys) + " |" for r in rows]
    return "\n".join([head, rule, *body])


MAX_GROUP_LABELS = 20  # x labels a breakdown panel shows (rotated, 7 pt: more overlap in a 5-inch panel)


def label_groups(ax, names: list[str]) -> None:
    """Name the groups 0..G-1 along ``ax``'s x axis: every k-th one, so that at most :data:`MAX_GROUP_LABELS` show."""
    step = -(-len(names) // MAX_GROUP_LABELS)
    shown = np.arange(0, len(names), max(step, 1))
    ax.set_xticks(shown, [names[i] for i in shown], rotation=60, ha="right", fontsize=7)


def plot_breakdowns(result, path: Path) -> Path:
    """NLL and hit rates per group for the main breakdowns, one panel each."""
    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    twins = []
    for ax, name in zip(axes.ravel(), PLOTTED):
        rows = result.breakdowns[name]  # every group: a scanner's 360 beams were drawn every 9th, unsaid
        x = np.arange(len(rows))
        many = len(rows) > MAX_GROUP_LABELS  # bars touch, hit rates without markers
        ax.bar(
            x,
            [r["nll"] for r in rows],
            width=1.0 if many else 0.8,
            lw=0,
            color="tab:red",
            alpha=0.7,
            label="NLL (nats/ray)",
        )
        ax.axhline(result.headline["nll"], color="k", lw=1, ls="--", label="overall NLL")
        # Rays that met no element are no step of the range, incidence or label axis: marks apart, not joined on.
        apart = x[[r["group"] == NO_ELEMENT_GROUP for r in rows]]
        joined = np.setdiff1d(x, apart)
        names = [r["group"] if r["group"] != NO_ELEMENT_GROUP else f"{r['group']} ({r['rays']:,} rays)" for r in rows]
        label_groups(ax, names)
        if apart.size:
            ax.axvline(apart[0] - 0.5, color="0.5", lw=0.8, ls=":")
        ax.set_title(f"by {name}")
        ax.set_ylabel("NLL (nats/ray)")
        twin = ax.twinx()
        twins.append(twin)
        ms = 0 if many else 3
        for key, style, color, text in (
            ("hit_rate_measured", "o-", "tab:blue", "hit rate measured"),
            ("hit_rate_simulated", "s--", "tab:green", "hit rate simulated"),
        ):
            twin.plot(joined, [rows[i][key] for i in joined], style, color=color, ms=ms, label=text)
            twin.plot(apart, [rows[i][key] for i in apart], style[0], color=color, ms=5)
        twin.set_ylim(-0.05, 1.05)  # a rate of 0 (the model never returns from nothing) shows whole
        twin.set_ylabel("hit rate")
    handles = axes[0, 0].get_legend_handles_labels()[0] + twins[0].get_legend_handles_labels()[0]
    fig.legend(handles, [h.get_label() for h in handles], loc="upper center", ncol=4)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return save_figure(fig, path)


def plot_residuals(t, path: Path) -> Path:
    """Histograms of measured and simulated ranges and of measured minus nominal range."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
    top = np.nanpercentile(np.concatenate([t.measured[t.hit], t.sim_range[t.sim_hit]]), 99.5) if t.hit.any() else 1
    bins = np.linspace(0, top, 80)
    a.hist(t.measured[t.hit], bins, alpha=0.6, label="measured", density=True)
    a.hist(t.sim_range[t.sim_hit], bins, alpha=0.6, label="simulated", density=True)
    a.set_xlabel("range (m)")
    a.set_ylabel("density (1/m)")
    a.set_title("range histograms")
    a.legend()
    res = (t.measured - t.nominal)[t.hit & np.isfinite(t.nominal)]
    lim = max(float(np.nanpercentile(np.abs(res), 98)), 1e-3) if res.size else 1
    b.hist(res, np.linspace(-lim, lim, 101), color="tab:purple")
    b.set_xlabel("measured - nominal range (m)")
    b.set_ylabel("returns")
    b.set_title("range residuals")
    fig.tight_layout()
    return save_figure(fig, path)


def plot_residual_image(t, shape: tuple, path: Path) -> Path:
    """The scan with the worst mean NLL as range images: measured and simulated side by side (one colour
    scale), the residual (measured - nominal) and the NLL per ray; black where there is no return."""
    s, h, w = shape
    scan = int(
        np.argmin(np.bincount(t.scan, weights=t.ll, minlength=s) / np.maximum(np.bincount(t.scan, minlength=s), 1))
    )
    m = t.scan == scan

    def image(values: np.ndarray) -> np.ndarray:
        out = np.full((h, w), np.nan)
        out[t.beam[m], t.column[m]] = values
        return out

    measured = image(np.where(t.hit[m], t.measured[m], np.nan))
    simulated = image(np.where(t.sim_hit[m], t.sim_range[m], np.nan))
    res = image(np.where(t.hit[m], t.measured[m] - t.nominal[m], np.nan))
    nll = image(-t.ll[m])
    if w == 1:  # a planar scan (N beams x 1 firing): curves over the beams, not images one pixel wide
        return _plot_beam_curves(scan, measured[:, 0], simulated[:, 0], res[:, 0], nll[:, 0], path)
    lim = max(float(np.nanpercentile(np.abs(res), 95)), 1e-3) if np.isfinite(res).any() else 1
    both = np.concatenate([measured[np.isfinite(measured)], simulated[np.isfinite(simulated)]])
    scale = dict(vmin=float(np.percentile(both, 1)), vmax=float(np.percentile(both, 99))) if both.size else {}
    fig, axes = plt.subplots(4, 1, figsize=(13, 9 if h > 1 else 6))
    for ax, picture, cmap, label, kw in (
        (axes[0], measured, "viridis", "measured range (m)", scale),
        (axes[1], simulated, "viridis", "simulated range (m)", scale),
        (axes[2], res, "coolwarm", "measured - nominal (m)", dict(vmin=-lim, vmax=lim)),
        (axes[3], nll, "magma", "NLL (nats)", {}),
    ):
        colours = matplotlib.colormaps[cmap].with_extremes(bad="black")
        im = ax.imshow(
            np.repeat(picture, max(1, 8 // h), axis=0) if h < 8 else picture,
            aspect="auto",
            cmap=colours,
            interpolation="nearest",
            **kw,
        )
        fig.colorbar(im, ax=ax).set_label(label, fontsize=8)
        ax.set_xlabel("firing (column)")
        ax.set_ylabel("beam" if h > 1 else "")
    axes[0].set_title(f"scan {scan}: measured and simulated (one draw) range images, residual, NLL (black: no return)")
    fig.tight_layout()
    return save_figure(fig, path)


def _plot_beam_curves(
    scan: int, measured: np.ndarray, simulated: np.ndarray, res: np.ndarray, nll: np.ndarray, path: Path
) -> Path:
    """:func:`plot_residual_image` of a scan of one firing: (beams,) ranges (m; NaN: no return), residual
    (m) and NLL (nats) drawn against the beam index, no-returns marked at the bottom of the range panel."""
    beams = np.arange(len(measured))
    fig, axes = plt.subplots(3, 1, figsize=(13, 7), sharex=True)
    top, middle, bottom = axes
    top.plot(beams, measured, ".", ms=3, color="black", label="measured")
    top.plot(beams, simulated, ".", ms=3, color="tab:red", alpha=0.6, label="simulated (one draw)")
    for values, colour, name in ((measured, "black", "measured"), (simulated, "tab:red", "simulated")):
        missed = ~np.isfinite(values)
        top.plot(beams[missed], np.zeros(missed.sum()), "|", ms=8, color=colour, label=f"{name}: no return")
    top.set_ylabel("range (m)")
    low, high = top.get_ylim()
    top.set_ylim(low, high + 0.3 * (high - low))  # headroom: the legend sat on the farthest ranges
    top.legend(fontsize=8, ncol=4, loc="upper right")
    middle.plot(beams, res, ".", ms=3, color="tab:purple")
    middle.axhline(0.0, color="grey", lw=0.6)
    middle.set_ylabel("measured - nominal (m)")
    bottom.plot(beams, nll, ".", ms=3, color="tab:orange")
    bottom.set_ylabel("NLL (nats)")
    bottom.set_xlabel("beam")
    top.set_title(f"scan {scan}: measured and simulated (one draw) ranges, residual and NLL per beam")
    fig.tight_layout()
    return save_figure(fig, path)


def beam_blocks_note(beams: list[dict], blocks: list[dict]) -> str:
    """The line above a beam breakdown listed in blocks: how many beams each row covers, where the rows per beam are.

    Args:
        beams: the breakdown's rows, one per beam.
        blocks: its rows per block of neighbouring beams (:func:`~mi_lidar.loop.compare.beam_blocks`).
    """
    sizes = sorted({b["beams"] for b in blocks})
    each = f"{sizes[-1]} neighbouring beams" + (f" ({sizes[0]} in the last)" if len(sizes) > 1 else "")
    return (
        f"{len(beams)} beams in {len(blocks)} rows of {each}, each over all rays of its beams; one row per beam: "
        "`comparison.json` (`breakdowns.beam`) and the figure's panel by beam."
    )


def write_residual_ply(t, log, path: Path) -> Path:
    """Measured points coloured by residual (red: long, blue: short), with residual and NLL."""
    from mi_lidar.io import write_ply

    points = log.points_world().reshape(-1, 3)[t.hit]
    res = np.nan_to_num((t.measured - t.nominal)[t.hit])
    lim = max(float(np.percentile(np.abs(res), 95)), 1e-3) if res.size else 1
    x = np.clip(res / lim, -1, 1)
    red = (255 * np.clip(x, 0, 1)).astype(np.uint8) + (127 * (1 - np.abs(x))).astype(np.uint8)
    blue = (255 * np.clip(-x, 0, 1)).astype(np.uint8) + (127 * (1 - np.abs(x))).astype(np.uint8)
    green = (127 * (1 - np.abs(x))).astype(np.uint8)
    return write_ply(
        path,
        points,
        {
            "red": red,
            "green": green,
            "blue": blue,
            "residual": res.astype(np.float32),
            "nll": (-t.ll[t.hit]).astype(np.float32),
        },
    )


def write_comparison(result, log, out: Path, title: str, model) -> list[Path]:
    """Write the comparison report into folder ``out``; return the files.

    The folder is made first and removed again while empty when a write fails (a full disk: it was left behind).
    """
    with output_folder(out):
        return _comparison_files(result, log, out, title, model)


def _comparison_files(result, log, out: Path, title: str, model) -> list[Path]:
    t = result.table
    from mi_lidar.loop.intensity_residuals import FIGURE, intensity_section

    files = [
        plot_breakdowns(result, out / "breakdowns.png"),
        plot_residuals(t, out / "residuals.png"),
        plot_residual_image(t, log.shape, out / "residual_image.png"),
    ]
    if t.hit.any():
        files.append(write_residual_ply(t, log, out / "residuals.ply"))
    files.append(write_json(out / "comparison.json", result.to_json(), default=float))
    h = result.headline
    keys = [
        "group",
        "breakdown",
        "rays",
        "nll",
        "excess_nll",
        "hit_rate_measured",
        "hit_rate_simulated",
        "range_error_median",
        "residual_median",
    ]
    lines = [
        f"# {title}",
        "",
        f"Model: range sigma {plain(model.range_sigma)} m, effects: {effects_text(model.effects)}. {h['rays']:,} rays.",
        "",
        *(f"**Warning:** {w}.\n" for w in result.warnings),
        f"**NLL {h['nll']:.3f} nats/ray** (median {h['nll_median']:.3f}); hit/miss F1 {fmt('f1', h['f1'])} "
        f"(precision {fmt('precision', h['precision'])}, recall {fmt('recall', h['recall'])}); "
        f"sampled range error median {fmt('range_error_median', h['range_error_median'])} m, "
        f"p90 {fmt('range_error_median', h['range_error_p90'])} m; "
        f"histogram L1 {fmt('histogram_l1', h['histogram_l1'])} m; Chamfer {h.get('chamfer', float('nan')):.3f} m; "
        f"hit rate measured "
        f"{h['hit_rate_measured']:.3f} vs simulated {h['hit_rate_simulated']:.3f}.",
        "",
        "## Where the model fails worst",
        "",
        "Groups with the largest excess NLL (group NLL minus overall NLL, times its rays):",
        "",
        markdown_table([dict(r, breakdown=words(r["breakdown"])) for r in result.worst], keys),
        "",
        "![breakdowns](breakdowns.png)",
        "",
        "![residuals](residuals.png)",
        "",
        "![residual image](residual_image.png)",
        "",
        "## Breakdowns",
    ]
    for name, rows in result.breakdowns.items():
        lines += ["", f"### By {words(name)}", ""]
        if name == "beam" and result.beam_blocks:
            lines += [beam_blocks_note(rows, result.beam_blocks), ""]
            rows = result.beam_blocks
        lines.append(markdown_table(rows, keys[:1] + keys[2:]))
    if any(r["group"] == NO_ELEMENT_GROUP for rows in result.breakdowns.values() for r in rows):
        lines += [
            "",
            f"Group `{NO_ELEMENT_GROUP}`: rays that meet no element of the scene within the sensor's range "
            "(the model expects no return).",
        ]
    lines += ["", "`residuals.ply`: measured points coloured by measured - nominal range (red long, blue short)."]
    md = "\n".join(lines) + "\n" + intensity_section(result.intensity, out)
    report = [
        atomic_write_text(out / "report.md", md),
        atomic_write_text(out / "report.html", markdown_to_html(md, title)),
    ]
    files += [out / FIGURE] if result.intensity is not None else []
    return files + report
