"""P-Reg (thesis ch. 3.3): P_null, mean and sigma of the return regressed on range and incidence.

For a segment at nominal range ``r`` and incidence ``delta`` the sensor loses the beam with
probability ``P_null(r, delta)`` and otherwise reports ``N(r + mu(r, delta), sigma(r, delta)^2)``.
The three functions are local linear kernel regressions (Gaussian kernels of bandwidths ``h_r``, m,
and ``h_delta``, deg) of the no-return indicator and the residual ``z - r`` (sigma^2: the residual's
scatter about the local line), tabulated on a grid of nodes and interpolated bilinearly; segments
of unknown incidence use a regression on range alone (of the training segments of unknown
incidence, or of all when there are none). A beam that met nothing misses with probability
``P_null`` of the escape state and otherwise returns uniformly on ``[0, z_max]``.

Choices where the thesis leaves room (documented and tested): the regressions pool the beams (the
density also reads per-beam tables, (beams, rows, nodes), which :func:`fit_p_reg` does not build);
the mean and sigma are fitted on returns within ``inlier`` (1 m) of the nominal range, so that the
5-10 % of real returns from objects the map lacks do not inflate sigma to metres; bandwidths are
chosen by held-out likelihood from a candidate set (:func:`fit_p_reg`); every node's estimates are
shrunk to the global ones with the weight of :data:`PSEUDO_SAMPLES` samples (as the protocol's
binned histograms are), and a local line is not followed beyond the range of its responses, so
sparse and empty nodes stay sane (:func:`_local_linear`). Ellipsoid elements keep their own Gaussian.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.densities.base import ESCAPE, UniformEscapeDensity, escape_segment, register_density
from mi_lidar.core.densities.samples import StateSamples, choose_by_held_out
from mi_lidar.core.densities.tables import check_table
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import ELLIPSOID, Segment

MIN_SIGMA = 1e-3  # m
PSEUDO_SAMPLES = 30.0  # every node's estimates are shrunk to the global ones with this many samples' weight


def _f(values) -> mi.Float:
    return mi.Float(aligned(np.asarray(values, np.float32).ravel()))


@register_density
class PRegDensity(UniformEscapeDensity):
    """Parametric regression density (see the module docstring); build it with :func:`fit_p_reg`."""

    name = "p_reg"
    learned = True
    specs = {
        "z_max": ParamSpec(80.0, "m", "largest range the sensor reports", lower=1e-3, upper=1e4, fit=False),
        "escape_null": ParamSpec(
            0.99, "1", "probability that a beam that met nothing is a miss", lower=0.0, upper=1.0, fit=False
        ),
    }

    def __init__(self, range_nodes=None, incidence_nodes=None, p_null=None, mu=None, sigma=None, **values):
        super().__init__(**values)
        self.range_nodes = np.asarray([0.0, 100.0] if range_nodes is None else range_nodes, np.float64)
        self.incidence_nodes = np.asarray([0.0, 90.0] if incidence_nodes is None else incidence_nodes, np.float64)
        shape = (self.incidence_nodes.size + 1, self.range_nodes.size)  # last row: unknown incidence
        self.p_null = np.asarray(np.zeros(shape) if p_null is None else p_null, np.float64)
        self.mu = np.asarray(np.zeros(shape) if mu is None else mu, np.float64)
        self.sigma = np.asarray(np.full(shape, 0.02) if sigma is None else sigma, np.float64)
        for name, table in (("p_null", self.p_null), ("mu", self.mu), ("sigma", self.sigma)):
            if table.shape[-2:] != shape or table.shape != self.p_null.shape or table.ndim not in (2, 3):
                raise ParameterError(
                    f"p_reg: table {name} has shape {table.shape}; expected {shape} or "
                    f"(beams, {shape[0]}, {shape[1]}), the shape of p_null {self.p_null.shape}"
                )
        check_table("p_reg", "range_nodes", self.range_nodes, increasing=True)
        check_table("p_reg", "incidence_nodes", self.incidence_nodes, increasing=True)
        check_table("p_reg", "p_null", self.p_null, lower=0.0, upper=1.0)
        check_table("p_reg", "mu", self.mu)
        check_table("p_reg", "sigma", self.sigma, lower=1e-9)
        self._tables = {k: _f(getattr(self, k)) for k in ("p_null", "mu", "sigma")}
        self._r, self._d = _f(self.range_nodes), _f(self.incidence_nodes)
        self.n_beams = 1 if self.p_null.ndim == 2 else self.p_null.shape[0]

    def tables(self) -> dict[str, np.ndarray]:
        return {
            "range_nodes": self.range_nodes,
            "incidence_nodes": self.incidence_nodes,
            "p_null": self.p_null,
            "mu": self.mu,
            "sigma": self.sigma,
        }

    @classmethod
    def from_tables(cls, params: dict, grid, tables: dict) -> PRegDensity:
        return cls(**tables, **params)

    # ------------------------------------------------------------------ interpolation
    def _locate(self, nodes: mi.Float, count: int, x: mi.Float):
        """Index of the node interval holding ``x`` (clamped) and the fraction within it."""
        i = dr.minimum(dr.binary_search(0, count - 1, lambda k: dr.gather(mi.Float, nodes, k + 1) <= x), count - 2)
        x0, x1 = dr.gather(mi.Float, nodes, i), dr.gather(mi.Float, nodes, i + 1)
        return i, dr.clip((x - x0) / (x1 - x0), 0.0, 1.0)

    def values(self, seg: Segment, rays: RayBatch) -> tuple[mi.Float, mi.Float, mi.Float]:
        """``(P_null, mu, sigma)`` of each lane, bilinear in (range, incidence); range only when unknown."""
        n_r, n_d = self.range_nodes.size, self.incidence_nodes.size
        i, t = self._locate(self._r, n_r, seg.nominal)
        delta = dr.acos(dr.clip(seg.cos_incidence, 0.0, 1.0)) * (180.0 / math.pi)
        j, s = self._locate(self._d, n_d, delta)
        unknown = dr.isnan(seg.cos_incidence)
        j = dr.select(unknown, n_d, j)
        s = dr.select(unknown, 0.0, s)
        j1 = dr.select(unknown, n_d, j + 1)
        beam = dr.minimum(rays.beam, self.n_beams - 1) if self.n_beams > 1 else 0
        base = beam * (n_d + 1) * n_r

        def at(table, row, col):
            return dr.gather(mi.Float, self._tables[table], base + row * n_r + col)

        out = []
        for name in ("p_null", "mu", "sigma"):
            low = (1 - t) * at(name, j, i) + t * at(name, j, i + 1)
            high = (1 - t) * at(name, j1, i) + t * at(name, j1, i + 1)
            out.append((1 - s) * low + s * high)
        return dr.clip(out[0], 0.0, 1.0 - 1e-6), out[1], dr.maximum(out[2], MIN_SIGMA)

    # ------------------------------------------------------------------ density interface
    def prepare(self, seg: Segment, rays: RayBatch) -> Segment:
        p_null, mu, sigma = self.values(seg, rays)
        surface = seg.kind == 0
        escape = seg.kind == ESCAPE
        null = dr.select(escape, self["escape_null"], p_null)
        return seg.with_(
            drop=dr.select(seg.kind != ELLIPSOID, 1.0 - (1.0 - seg.drop) * (1.0 - null), seg.drop),
            mean=dr.select(surface, seg.mean + mu, seg.mean),
            sigma=dr.select(surface, sigma, seg.sigma),
        )

    def escape(self, rays: RayBatch) -> Segment:
        return escape_segment(rays, sigma=1.0)


# ---------------------------------------------------------------------- fitting
def _local_linear(
    x: np.ndarray,
    y: np.ndarray,
    w: np.ndarray,
    nodes: list[np.ndarray],
    bandwidths: list[float],
    y2: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Local linear kernel regression of ``y`` on ``x`` (N, D) with sample weights ``w``, at a node grid.

    At every node the weighted least-squares line's value there is the estimate, kept within the range
    of the responses that carry the node's kernel weight (a local line may not leave its data far from
    them, where a node outside the data would otherwise extrapolate a slope to metres). The scatter
    about that line, ``sum k (y2 - 2 y line + line^2) / sum k``, is the local variance: never negative,
    unlike the difference of two separately regressed moments, which at sparse nodes collapsed sigma to
    its 1 mm floor.

    Args:
        x, y, w: (N, D) states, (N,) responses and (N,) weights (binned samples: cell means and counts).
        nodes, bandwidths: the node coordinates per dimension and the Gaussian kernel's bandwidths.
        y2: (N,) mean of the squared response per sample (its cell); default ``y ** 2``.

    Returns:
        (estimate, local variance), each of the grid's shape (product of the node counts); nodes
        without weight get the global mean and variance, nodes where the system is singular the local mean.
    """
    y2 = y * y if y2 is None else y2
    grid = np.stack(np.meshgrid(*nodes, indexing="ij"), axis=-1).reshape(-1, len(nodes))
    out, variance = np.empty(len(grid)), np.empty(len(grid))
    global_mean = float(np.average(y, weights=w)) if w.sum() > 0 else 0.0
    global_variance = max(float(np.average(y2, weights=w)) - global_mean**2, 0.0) if w.sum() > 0 else 0.0
    for g, node in enumerate(grid):
        d = (x - node) / np.asarray(bandwidths)
        k = w * np.exp(-0.5 * np.sum(d * d, axis=1))
        total = k.sum()
        if total < 1e-9:
            out[g], variance[g] = global_mean, global_variance
            continue
        design = np.concatenate([np.ones((len(x), 1)), x - node], axis=1)
        a = design.T @ (design * k[:, None])
        b = design.T @ (k * y)
        try:
            coef = np.linalg.solve(a + 1e-9 * np.eye(len(a)) * total, b)
        except np.linalg.LinAlgError:
            coef = np.zeros(len(a))
            coef[0] = float(np.dot(k, y) / total)
        weighty = k >= 1e-3 * k.max()
        coef[0] = np.clip(coef[0], y[weighty].min(), y[weighty].max())
        line = design @ coef
        local_variance = max(float(np.dot(k, y2 - 2.0 * y * line + line * line) / total), 0.0)
        out[g] = (total * coef[0] + PSEUDO_SAMPLES * global_mean) / (total + PSEUDO_SAMPLES)
        variance[g] = (total * local_variance + PSEUDO_SAMPLES * global_variance) / (total + PSEUDO_SAMPLES)
    shape = [len(n) for n in nodes]
    return out.reshape(shape), variance.reshape(shape)


def fit_p_reg(
    samples: StateSamples,
    held_out_score: Callable[[PRegDensity], float],
    h_ranges=(0.5, 1.0, 2.0, 4.0),
    h_incidences=(5.0, 10.0, 20.0),
    inlier: float = 1.0,
    z_max: float = 80.0,
    range_nodes: np.ndarray | None = None,
    incidence_nodes: np.ndarray | None = None,
    progress=None,
) -> tuple[PRegDensity, list]:
    """P-Reg: local linear regressions of P_null, mu and sigma; bandwidths chosen by held-out likelihood.

    Args:
        samples: training states and measurements (:class:`StateSamples`).
        held_out_score: mean held-out NLL (nats per ray) of a candidate density (the one likelihood).
        h_ranges, h_incidences: candidate bandwidths, m and deg.
        inlier: returns within this distance of the nominal range (m) fit mu and sigma.
        z_max: largest reported range, m.
        range_nodes, incidence_nodes: tabulation nodes (default: every 0.5 m to the farthest
            nominal range, every 5 deg).
        progress: optional ``progress(done, total)``.

    Returns:
        The best density and the table of candidates ``(h_range, h_incidence, NLL)``.
    """
    met = samples.met
    r, d, hit, e = samples.nominal[met], samples.incidence[met], samples.hit[met], samples.residual[met]
    far = float(np.nanmax(r)) if r.size else 10.0
    r_nodes = np.arange(0.0, far + 0.5, 0.5) if range_nodes is None else np.asarray(range_nodes)
    d_nodes = np.arange(0.0, 90.0 + 1e-9, 5.0) if incidence_nodes is None else np.asarray(incidence_nodes)
    # fine bins keep the regression cheap: per bin, the mean state and the mean of each response
    known = ~np.isnan(d)
    inl = hit & (np.abs(np.nan_to_num(e, nan=np.inf)) <= inlier)
    escape_null = float(np.mean(~samples.hit[~met])) if np.any(~met) else 0.99
    candidates = list(itertools.product(h_ranges, h_incidences))

    def build(h_r: float, h_d: float) -> PRegDensity:
        shape = (d_nodes.size + 1, r_nodes.size)
        tables = {k: np.zeros(shape) for k in ("p_null", "mu", "sigma")}
        for row, mask, x, nodes, bws in (
            ("known", known, np.stack([d, r], 1), [d_nodes, r_nodes], [h_d, h_r]),
            ("unknown", ~known if np.any(~known) else known, r[:, None], [r_nodes], [h_r]),
        ):
            xm, missed, counts, _ = _binned(x[mask], (~hit[mask]).astype(float), nodes)
            p_null, _ = _local_linear(xm, missed, counts, nodes, bws)
            xm, em, counts, e2m = _binned(x[mask & inl], e[mask & inl], nodes)
            mu, variance = _local_linear(xm, em, counts, nodes, bws, y2=e2m)
            sigma = np.sqrt(np.maximum(variance, MIN_SIGMA**2))
            target = slice(0, d_nodes.size) if row == "known" else slice(d_nodes.size, d_nodes.size + 1)
            for name, values in (("p_null", p_null), ("mu", mu), ("sigma", sigma)):
                tables[name][target] = values.reshape(-1, r_nodes.size)
        return PRegDensity(
            range_nodes=r_nodes,
            incidence_nodes=d_nodes,
            p_null=np.clip(tables["p_null"], 0, 1),
            mu=tables["mu"],
            sigma=tables["sigma"],
            z_max=z_max,
            escape_null=escape_null,
        )

    return choose_by_held_out(candidates, build, held_out_score, progress)


def _binned(
    x: np.ndarray, y: np.ndarray, nodes: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Aggregate samples into cells of half the node spacing: cell means of x and y, counts, cell means of y^2."""
    if len(x) == 0:
        return np.zeros((0, len(nodes))), np.zeros(0), np.zeros(0), np.zeros(0)
    steps = [max(float(np.median(np.diff(n))) / 2.0, 1e-6) if n.size > 1 else 1.0 for n in nodes]
    keys = np.stack([np.floor(x[:, k] / steps[k]) for k in range(len(nodes))], 1).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    xm = np.stack([np.bincount(inverse, x[:, k]) / counts for k in range(len(nodes))], 1)
    return xm, np.bincount(inverse, y) / counts, counts.astype(float), np.bincount(inverse, y * y) / counts
