"""Intensity residuals of a model against a log: per return, by range, incidence, beam and label, as a figure.

``compare`` and ``diagnose`` show them beside the range residuals whenever the log carries an
intensity (:func:`intensity_attribute`). For each measured return the first element along its ray
is traced (after the model's ray perturbations); the return counts when that element explains its
range (within :data:`~mi_lidar.loop.residuals.NEAR` of the element's nominal range, as in the range
channel of :mod:`mi_lidar.loop.residuals`). Per return:

* **expected**: the element's noise-free intensity under the model's
  :class:`~mi_lidar.core.intensity.IntensityModel` (its reflectivity, range, incidence, beam gain);
* **ratio**: ``(measured + 1) / (expected + 1)``, the factor by which the model is off (``+ 1``
  keeps dark returns finite);
* **NLL**: ``-log g(I)``, the intensity's negative log-likelihood at that element (nats per return,
  one-unit bins), the factor the joint likelihood multiplies the range density by;
* **simulated**: one intensity the model samples for the same ray (same seed as the range
  simulation of ``compare``), whose histogram is drawn beside the measured one.

The groups are those of ``compare``'s range breakdowns (:func:`~mi_lidar.loop.compare.group_keys`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.elements import ElementTable
from mi_lidar.core.log import Log
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.trace import next_intersection
from mi_lidar.io.cloud import INTENSITY_SOURCES
from mi_lidar.loop.compare import group_keys, group_order
from mi_lidar.loop.report import label_groups, markdown_table
from mi_lidar.loop.residuals import NEAR

BREAKDOWNS = ("range", "incidence", "beam", "label")
FIGURE = "intensity_residuals.png"


def intensity_attribute(log: Log, law: str) -> str | None:
    """The log attribute holding intensities in the scale of an intensity law, or None.

    ``intensity`` first, then the attribute named as the law (an Ouster log's ``reflectivity`` or
    ``signal``), then any of :data:`~mi_lidar.io.cloud.INTENSITY_SOURCES`.
    """
    for name in ("intensity", law, *INTENSITY_SOURCES):
        if name in log.attributes:
            return name
    return None


def first_element_intensity(scene, table: ElementTable, model: SensorModel, rays: LogRays, index: np.ndarray) -> dict:
    """The first element along each ray of ``index`` and the model's intensity there.

    Args:
        scene, table: the scene and its element table.
        model: the sensor model (its ray perturbations and intensity model).
        rays: the log's rays with intensities (``LogRays.from_log(log, intensity=...)``).
        index: (M,) ray indices.

    Returns:
        ``met`` (M,) the ray meets an element; and, NaN where it does not: ``expected`` intensity
        (sensor units), ``log_g`` (log density of the measured intensity, one-unit bins),
        ``nominal`` range (m), ``cos_incidence``; ``label`` (-1 where none).
    """
    batch, _, _ = rays.batch(index)
    batch = model.prepare_rays(batch)
    with dr.suspend_grad():
        si, valid, element = next_intersection(
            scene, table, batch.origin, batch.origin, batch.direction, model.max_range
        )
        seg = table.traced_segment(si, valid, element, batch.origin, batch.direction, model.range_sigma)
        measured = np.nan_to_num(rays.intensity[index]).astype(np.float32)
        expected = model.intensity.expected(seg, batch)
        log_g = model.intensity.log_prob(seg, mi.Float(measured), batch)
    met = np.asarray(valid)
    return {
        "met": met,
        "expected": np.where(met, np.asarray(expected), np.nan),
        "log_g": np.where(met, np.asarray(log_g), np.nan),
        "nominal": np.where(met, np.asarray(seg.nominal), np.nan),
        "cos_incidence": np.where(met, np.asarray(seg.cos_incidence), np.nan),
        "label": np.where(met, np.asarray(seg.label).astype(np.int64), -1),
    }


@dataclass
class IntensityResiduals:
    """Measured and modelled intensities of the returns whose first element explains their range.

    The per-return arrays carry the fields :func:`~mi_lidar.loop.compare.group_keys` reads, so the
    groups are the range breakdown's.

    Attributes:
        attribute: the log attribute compared (``intensity``, ``reflectivity``, ``signal``).
        measured, expected, log_g: (N,) measured and expected intensity (sensor units), log density of
            the measured one (nats, one-unit bins).
        nominal, cos_incidence, beam, label, kind: (N,) of the first element and the ray.
        simulated: (K,) intensities the model sampled at returns it simulated on the same rays.
    """

    attribute: str
    measured: np.ndarray
    expected: np.ndarray
    log_g: np.ndarray
    nominal: np.ndarray
    cos_incidence: np.ndarray
    beam: np.ndarray
    label: np.ndarray
    kind: np.ndarray
    simulated: np.ndarray

    @property
    def channel(self) -> str:
        """``intensity``, or ``intensity (reflectivity)`` when the log's attribute has another name."""
        return "intensity" if self.attribute == "intensity" else f"intensity ({self.attribute})"

    @property
    def ratio(self) -> np.ndarray:
        """(N,) ``(measured + 1) / (expected + 1)``."""
        return (self.measured + 1.0) / (self.expected + 1.0)

    def metrics(self, keep: np.ndarray | None = None) -> dict:
        """Returns, medians of measured and expected intensity and of the ratio, ratio quartiles, NLL."""
        keep = np.ones(self.measured.size, bool) if keep is None else keep
        ratio, nan = self.ratio[keep], float("nan")
        quartiles = np.quantile(ratio, [0.25, 0.75]) if ratio.size else (nan, nan)
        return {
            "returns": int(keep.sum()),
            "intensity_measured": float(np.median(self.measured[keep])) if ratio.size else nan,
            "intensity_expected": float(np.median(self.expected[keep])) if ratio.size else nan,
            "intensity_ratio": float(np.median(ratio)) if ratio.size else nan,
            "intensity_ratio_q1": float(quartiles[0]),
            "intensity_ratio_q3": float(quartiles[1]),
            "intensity_nll": float(-np.mean(self.log_g[keep])) if ratio.size else nan,
        }

    def breakdown(self, by: str) -> list[dict]:
        """:meth:`metrics` per group of breakdown ``by`` (one of :data:`BREAKDOWNS`)."""
        keys = group_keys(self, by)
        return [{"group": str(k), **self.metrics(keys == k)} for k in sorted(np.unique(keys), key=group_order)]

    def to_json(self) -> dict:
        return {
            "attribute": self.attribute,
            "headline": self.metrics(),
            "simulated_median": float(np.median(self.simulated)) if self.simulated.size else float("nan"),
            "breakdowns": {by: self.breakdown(by) for by in BREAKDOWNS},
        }


def intensity_residuals(
    log: Log, scene, model: SensorModel, index: np.ndarray | None = None, seed: int = 0
) -> IntensityResiduals | None:
    """Intensity residuals of ``model`` on the rays ``index`` of ``log`` (all when None).

    Returns:
        The :class:`IntensityResiduals`, or None when the log carries no intensity or none of its
        returns is explained by the element its ray meets first.
    """
    attribute = intensity_attribute(log, model.intensity.choices["law"])
    if attribute is None:
        return None
    rays = LogRays.from_log(log, intensity=attribute, scene=scene)
    index = np.arange(rays.n) if index is None else np.asarray(index)
    index = index[rays.hit[index] & np.isfinite(rays.intensity[index])]
    table = ElementTable.from_scene(scene)
    first = first_element_intensity(scene, table, model, rays, index)
    explained = first["met"] & (np.abs(rays.measured[index] - np.nan_to_num(first["nominal"])) < NEAR)
    if not explained.any():
        return None
    simulated = []
    for start in range(0, index.size, 1 << 21):
        batch, _, _ = rays.batch(index[start : start + (1 << 21)])
        out = model.simulate_rays(scene, table, batch, seed)
        simulated.append(np.asarray(out["intensity"])[np.asarray(out["hit"])])
    keep = index[explained]
    return IntensityResiduals(
        attribute=attribute,
        measured=rays.intensity[keep].astype(np.float64),
        expected=first["expected"][explained],
        log_g=first["log_g"][explained],
        nominal=first["nominal"][explained],
        cos_incidence=first["cos_incidence"][explained],
        beam=rays.beam[keep],
        label=first["label"][explained],
        kind=np.zeros(keep.size, np.int64),
        simulated=np.concatenate(simulated),
    )


def plot_intensity_residuals(res: IntensityResiduals, path: Path) -> Path:
    """Measured against expected intensity, measured and simulated histograms, and the ratio by range,
    incidence, beam and label (median with quartiles); PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from mi_lidar.core.atomic import atomic_path

    ticks = matplotlib.ticker.FuncFormatter(lambda value, _: f"{value:.3g}")  # log minor ticks 1.05, 1.07: apart
    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    ax = axes[0, 0]
    top = float(max(res.measured.max(), res.expected.max())) + 1.0
    ax.scatter(res.measured + 1.0, res.expected + 1.0, s=2, alpha=0.3, lw=0)
    ax.plot([1, top], [1, top], color="k", lw=0.8)
    ax.set(xscale="log", yscale="log", xlabel=f"measured {res.attribute} + 1", ylabel="expected + 1")
    ax.set_title(f"per return (NLL {res.metrics()['intensity_nll']:.2f} nats/return)")
    ax = axes[0, 1]
    bins = np.linspace(0.0, float(np.quantile(np.concatenate([res.measured, res.simulated]), 0.995)) + 1.0, 60)
    ax.hist(res.measured, bins, alpha=0.6, density=True, label="measured")
    ax.hist(res.simulated, bins, alpha=0.6, density=True, label="simulated (one draw)")
    ax.set(xlabel=res.attribute, ylabel="density", title="intensity histograms")
    ax.legend()
    for ax, by in zip([axes[0, 2], *axes[1]], BREAKDOWNS):
        rows = res.breakdown(by)
        if len(rows) > 40:
            rows = rows[:: max(1, len(rows) // 40)]
        x = np.arange(len(rows))
        median = np.array([r["intensity_ratio"] for r in rows])
        spread = np.array([[m - r["intensity_ratio_q1"], r["intensity_ratio_q3"] - m] for m, r in zip(median, rows)])
        ax.errorbar(x, median, yerr=spread.T, fmt="o", ms=3, color="tab:purple")
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ticks)
        ax.yaxis.set_minor_formatter(ticks)
        label_groups(ax, [r["group"] for r in rows])
        ax.set(ylabel="(measured + 1) / (expected + 1)", title=f"by {by} (median, quartiles)")
    fig.suptitle(f"{res.channel.capitalize()}: returns whose range the first element explains")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path


def intensity_section(res: IntensityResiduals | None, out: Path) -> str:
    """The Markdown section of a report on ``res`` (its figure written into ``out``); '' when None."""
    if res is None:
        return ""
    plot_intensity_residuals(res, Path(out) / FIGURE)
    head = res.metrics()
    keys = ["group", "returns", "intensity_measured", "intensity_expected", "intensity_ratio", "intensity_nll"]
    lines = [
        "",
        f"## {res.channel.capitalize()}",
        "",
        f"{head['returns']:,} returns whose range the first element explains: median measured "
        f"{head['intensity_measured']:.1f}, expected {head['intensity_expected']:.1f}; measured / expected "
        f"(+1) median {head['intensity_ratio']:.2f} (quartiles {head['intensity_ratio_q1']:.2f}-"
        f"{head['intensity_ratio_q3']:.2f}); **intensity NLL {head['intensity_nll']:.3f} nats/return**; "
        f"simulated median {np.median(res.simulated) if res.simulated.size else float('nan'):.1f}.",
        "",
        f"![intensity residuals]({FIGURE})",
    ]
    for by in BREAKDOWNS:
        lines += ["", f"### Intensity by {by}", "", markdown_table(res.breakdown(by), keys)]
    return "\n".join(lines) + "\n"
