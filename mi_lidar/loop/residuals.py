"""Structure left in a model's residuals: does the log still differ from the model along some dimension?

After diagnosis the model is simulated at the held-out rays and compared with the measurements
group by group along five dimensions (time, azimuth, beam, nominal range, label), on two channels:

* ``range``: the mean range residual ``z - r0`` (``r0`` the nominal range of the ray's first
  element), over returns within :data:`NEAR` of ``r0``, measured minus simulated;
* ``returns``: the return rate, measured minus simulated.

A model that lacks nothing leaves differences that are constant up to sampling noise. For each
dimension and channel the groups' differences are tested against their common weighted mean
(chi-square with ``groups - 1`` degrees of freedom); a dimension is flagged when ``p <`` :data:`P_STRUCTURE`
and the groups' spread beyond their sampling noise (RMS) exceeds a size that matters
(:data:`MIN_RANGE_DEPARTURE`, :data:`MIN_RATE_DEPARTURE`). The verdict names the dimension, the
closest catalog effect and where to read how to write a new one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from mi_lidar.io.markdown import p_phrase

P_STRUCTURE = 1e-6
NEAR = 0.5  # m: returns this close to the first element's nominal range enter the range channel
MIN_RANGE_DEPARTURE = 0.003  # m: RMS spread of the groups' range differences beyond their noise
MIN_RATE_DEPARTURE = 0.01  # the same for return-rate differences
MIN_GROUP = 30  # rays a group needs to be tested
DIMENSIONS = ("time", "azimuth", "beam", "range", "label")
CLOSEST = {
    ("range", "time"): "range_bias (constant in time) or motion_distortion",
    ("range", "azimuth"): "extrinsics",
    ("range", "beam"): "range_bias",
    ("range", "range"): "range_scale",
    ("range", "label"): "range_bias",
    ("returns", "time"): "random_dropout (constant in time)",
    ("returns", "azimuth"): "extrinsics",
    ("returns", "beam"): "beam_offsets",
    ("returns", "range"): "range_dropout",
    ("returns", "label"): "label_dropout",
}
GUIDE = "docs/writing_an_effect.md"
PARAGRAPH = "\n\n"  # between the paragraphs of a verdict: Markdown paragraphs, separate lines in a terminal
MANY_GROUPS = 32  # a panel of more groups (a scanner's beams) draws a band of 2 standard errors, not a bar each
UNITS = {"time": "s", "azimuth": "deg", "beam": "", "range": "m", "label": "", "incidence": "deg"}


@dataclass
class Structure:
    """Residual structure along one dimension and channel.

    Attributes:
        dimension: one of :data:`DIMENSIONS`.
        channel: ``range`` (mean residual, m) or ``returns`` (return rate).
        centers: (G,) group centres (s, deg, beam, m, label).
        difference: (G,) measured minus simulated, per group.
        error: (G,) standard error of each difference.
        chi2, dof, p_value: the test of equal differences.
        departure: RMS spread of the differences around their weighted mean beyond the groups'
            sampling noise (m or rate).
        flagged: the model misses something along this dimension.
    """

    dimension: str
    channel: str
    centers: np.ndarray
    difference: np.ndarray
    error: np.ndarray
    chi2: float
    dof: int
    p_value: float
    departure: float
    flagged: bool

    def row(self) -> dict:
        return {
            "dimension": self.dimension,
            "channel": self.channel,
            "chi2": self.chi2,
            "dof": self.dof,
            "p_value": self.p_value,
            "departure": self.departure,
            "flagged": self.flagged,
        }


def group_index(dimension: str, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(group index per ray, -1 where the value is unknown; group centres) for ``values`` along ``dimension``.

    Beams and labels are their own groups, azimuth has 12 sectors of 30 deg, any other dimension 12
    groups of equal counts.
    """
    if dimension in ("beam", "label"):
        centers, index = np.unique(values, return_inverse=True)
        return index, centers.astype(float)
    if dimension == "azimuth":
        edges = np.linspace(-180.0, 180.0, 13)
    else:
        finite = values[np.isfinite(values)]
        edges = np.unique(np.quantile(finite, np.linspace(0, 1, 13))) if finite.size else np.array([0.0, 1.0])
    index = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
    return np.where(np.isfinite(values), index, -1), 0.5 * (edges[:-1] + edges[1:])


def _test(index, centers, measured, simulated, measured_ok, simulated_ok, minimum) -> tuple:
    diff, err, keep = [], [], []
    for g in range(len(centers)):
        a, b = measured[(index == g) & measured_ok], simulated[(index == g) & simulated_ok]
        if a.size < MIN_GROUP or b.size < MIN_GROUP:
            continue
        keep.append(g)
        diff.append(a.mean() - b.mean())
        err.append(np.sqrt(max(a.var() / a.size + b.var() / b.size, 1e-12)))
    diff, err = np.asarray(diff), np.asarray(err)
    if diff.size < 2:
        return centers[keep], diff, err, 0.0, 0, 1.0, 0.0, False
    weight = 1.0 / err**2
    mean = float(np.sum(weight * diff) / weight.sum())
    chi2 = float(np.sum(((diff - mean) / err) ** 2))
    dof = diff.size - 1
    p = float(stats.chi2.sf(chi2, dof))
    # spread of the groups beyond their sampling noise (the largest single group is noise among many)
    departure = float(np.sqrt(max(np.sum(weight * (diff - mean) ** 2) / weight.sum() - np.mean(err**2), 0.0)))
    return centers[keep], diff, err, chi2, dof, p, departure, bool(p < P_STRUCTURE and departure > minimum)


def residual_structure(
    dimensions: dict[str, np.ndarray],
    nominal: np.ndarray,
    measured: np.ndarray,
    hit: np.ndarray,
    sim_range: np.ndarray,
    sim_hit: np.ndarray,
) -> list[Structure]:
    """Test measured against simulated returns for structure along every dimension.

    Args:
        dimensions: ``{dimension: (N,) value per ray}`` (time s, azimuth deg, beam, range m, label).
        nominal: (N,) nominal range of each ray's first element, m (NaN where none).
        measured, hit: (N,) measured range (m) and return flag.
        sim_range, sim_hit: (N,) simulated range (m) and return flag, same rays.

    Returns:
        One :class:`Structure` per dimension and channel, flagged ones first (most significant first).
    """
    near_m = hit & np.isfinite(nominal) & (np.abs(measured - nominal) < NEAR)
    near_s = sim_hit & np.isfinite(nominal) & (np.abs(sim_range - nominal) < NEAR)
    res_m, res_s = np.where(near_m, measured - nominal, 0.0), np.where(near_s, sim_range - nominal, 0.0)
    traced = np.isfinite(nominal)
    out = []
    for dimension, values in dimensions.items():
        index, centers = group_index(dimension, np.asarray(values, float))
        for channel, args, minimum in (
            ("range", (res_m, res_s, near_m, near_s), MIN_RANGE_DEPARTURE),
            ("returns", (hit.astype(float), sim_hit.astype(float), traced, traced), MIN_RATE_DEPARTURE),
        ):
            c, d, e, chi2, dof, p, departure, flagged = _test(index, centers, *args, minimum)
            out.append(Structure(dimension, channel, c, d, e, chi2, dof, p, departure, flagged))
    return sorted(out, key=lambda s: (not s.flagged, s.p_value))


def departure_text(s: Structure, digits: int) -> str:
    """``s.departure`` in the units a reader compares: cm for ranges, percentage points for return rates."""
    return f"{100 * s.departure:.{digits}f} {'cm' if s.channel == 'range' else 'points'}"


def structure_verdict(found: list[Structure]) -> str:
    """The plain-words paragraphs for the flagged dimensions, one each, then what to do ('' when none).

    The paragraphs are separated by a blank line (Markdown paragraphs; a line each in a terminal): six
    flagged dimensions made one paragraph of 20 terminal lines that said six times where the guide is.
    """
    flagged = [s for s in found if s.flagged]
    if not flagged:
        return ""
    parts = []
    for s in flagged:
        what = (
            f"measured ranges depart from the model's by {departure_text(s, 1)} RMS across the groups"
            if s.channel == "range"
            else f"the return rate departs from the model's by {departure_text(s, 1)} RMS across the groups"
        )
        parts.append(
            f"The model still misses something that varies with {s.dimension}; no catalog effect explains it "
            f"({what}; chi2 {s.chi2:.0f} for {s.dof} degrees of freedom, {p_phrase(s.p_value, 1)}). "
            f"The closest catalog effect is {CLOSEST[(s.channel, s.dimension)]}."
        )
    what = "it" if len(flagged) == 1 else "what no catalog effect explains"
    parts.append(f"To model {what}, write a new effect ({GUIDE}).")
    return PARAGRAPH.join(parts)


def plot_structure(found: list[Structure], path: Path) -> Path:
    """Measured minus simulated per group along every dimension (flagged panels in red); PNG at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_lidar.loop.report import save_figure

    by_key = {(s.channel, s.dimension): s for s in found if s.difference.size}
    shown = [d for d in DIMENSIONS if any((channel, d) in by_key for channel in ("range", "returns"))]
    shown = shown or [DIMENSIONS[0]]  # nothing grouped: one panel, hidden
    fig, axes = plt.subplots(2, len(shown), figsize=(3.2 * len(shown) + 1.0, 5.2), squeeze=False)
    for row, channel in enumerate(("range", "returns")):
        for col, dimension in enumerate(shown):
            ax = axes[row, col]
            s = by_key.get((channel, dimension))
            if s is None:
                ax.set_visible(False)
                continue
            scale = 100.0  # cm or percentage points
            colour = "tab:red" if s.flagged else "tab:blue"
            ax.set_xlabel(f"{dimension} ({UNITS[dimension]})" if UNITS[dimension] else dimension)
            if s.dof == 0:  # one group (one label in the scene): nothing to compare it with
                ax.set_xticks([])
                ax.set_yticks([])
                ax.text(0.5, 0.5, f"one {dimension} group:\nnothing to compare", ha="center", transform=ax.transAxes)
                continue
            ax.axhline(0.0, color="grey", lw=0.6)
            y, e = scale * s.difference, 2 * scale * s.error
            if s.centers.size > MANY_GROUPS:  # 180 error bars are a solid smear: a line in a band
                ax.fill_between(s.centers, y - e, y + e, color=colour, alpha=0.25, lw=0)
                ax.plot(s.centers, y, "-", color=colour, lw=0.8)
            else:
                ax.errorbar(s.centers, y, yerr=e, fmt="o-", color=colour, ms=3)
            low, high = ax.get_ylim()  # at least +-1 cm / point, so that agreement looks flat
            ax.set_ylim(min(low, -1.0), max(high, 1.0))
            ax.set_title(p_phrase(s.p_value, 1), fontsize=8, color=colour)
            if col == 0:
                ax.set_ylabel("range residual, cm" if channel == "range" else "return rate, points")
    fig.suptitle("Measured minus model, per group (bars or band: 2 standard errors; red: structure left)")
    fig.tight_layout()
    return save_figure(fig, path)
