"""P-Reg (thesis ch. 3.3): P_null, mean and sigma of the return regressed on range and incidence.

For a segment at nominal range ``r`` and incidence ``delta`` the sensor loses the beam with
probability ``P_null(r, delta)`` and otherwise reports ``N(r + mu(r, delta), sigma(r, delta)^2)``.
The three functions are local linear kernel regressions (Gaussian kernels of bandwidths ``h_r``, m,
and ``h_delta``, deg) of the no-return indicator and the residual ``z - r`` (sigma^2: the residual's
scatter about the local line), tabulated on a grid of nodes and interpolated bilinearly; segments
of unknown incidence use a regression on range alone (of the training segments of unknown
incidence, or of all when there are none). A beam that met nothing misses with probability
``P_null`` of the escape state and otherwise reports, with ``escape=gaussian``, ``N(escape_mean,
escape_sigma^2)``: the mean and spread of the training returns of such beams, shrunk to those of the
uniform law on ``[0, z_max]`` with the weight of :data:`PSEUDO_SAMPLES` returns; with
``escape=uniform``, a range uniform on ``[0, z_max]`` (what a file written before the choice holds).
:func:`fit_p_reg` takes whichever scores better held out: the Gaussian where the scene misses objects
the sensor sees (a crude 3D scene's escaped beams return at 5-30 m, not anywhere to 120 m), the
uniform where escaped returns are spurious readings spread over the sensor's span.

Choices where the thesis leaves room (documented and tested): the regressions pool the beams and
the labels unless told to keep ``n_labels`` labels and ``n_beams`` beams apart; then the groups form
a hierarchy, each label's regressions shrunk to the pooled ones and each beam's (within its label) to
its label's, every group's prior being its own level shrunk to its parent's (:func:`_level_prior`),
and the density reads the tables of a segment's group (label x beam, its
:class:`StateGrid`); the mean and sigma are fitted on returns
within ``inlier`` (1 m) of the nominal range, so that the 5-10 % of real returns from objects the
map lacks do not inflate sigma to metres; bandwidths are chosen by held-out likelihood from a
candidate set (:func:`fit_p_reg`); every node's estimates are shrunk to the global (or pooled) ones
with the weight of :data:`PSEUDO_SAMPLES` samples (as the protocol's binned histograms are), and a
local line is not followed far beyond its data, so sparse and empty nodes stay sane
(:func:`_local_linear`). Ellipsoid elements keep their own Gaussian.
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
from mi_lidar.core.densities.samples import StateSamples, choose_then_vary
from mi_lidar.core.densities.tables import PSEUDO_SAMPLES, StateGrid, check_table
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import ELLIPSOID, Segment, incidence_deg, log_density, sample_range, window_probability

MIN_SIGMA = 1e-3  # m
REACH = 2.0  # a local line is followed at most this many weighted standard deviations beyond its data's mean


def _f(values) -> mi.Float:
    return mi.Float(aligned(np.asarray(values, np.float32).ravel()))


@register_density
class PRegDensity(UniformEscapeDensity):
    """Parametric regression density (see the module docstring); build it with :func:`fit_p_reg`."""

    name = "p_reg"
    learned = True
    options = {"escape": ("uniform", "gaussian")}
    specs = {
        "z_max": ParamSpec(80.0, "m", "largest range the sensor reports", lower=1e-3, upper=1e4, fit=False),
        "escape_null": ParamSpec(
            0.99, "1", "probability that a beam that met nothing is a miss", lower=0.0, upper=1.0, fit=False
        ),
        "escape_mean": ParamSpec(
            40.0, "m", "mean range a beam that met nothing reports", fit=False, only={"escape": ("gaussian",)}
        ),
        "escape_sigma": ParamSpec(
            23.1,
            "m",
            "spread of the range a beam that met nothing reports",
            lower=MIN_SIGMA,
            fit=False,
            only={"escape": ("gaussian",)},
        ),
    }

    def __init__(self, range_nodes=None, incidence_nodes=None, p_null=None, mu=None, sigma=None, grid=None, **values):
        super().__init__(**values)
        self.range_nodes = np.asarray([0.0, 100.0] if range_nodes is None else range_nodes, np.float64)
        self.incidence_nodes = np.asarray([0.0, 90.0] if incidence_nodes is None else incidence_nodes, np.float64)
        shape = (self.incidence_nodes.size + 1, self.range_nodes.size)  # last row: unknown incidence
        self.p_null = np.asarray(np.zeros(shape) if p_null is None else p_null, np.float64)
        self.mu = np.asarray(np.zeros(shape) if mu is None else mu, np.float64)
        self.sigma = np.asarray(np.full(shape, 0.02) if sigma is None else sigma, np.float64)
        if grid is None:  # a file written before the grid was saved: per-beam tables, or one group
            grid = StateGrid(n_beams=self.p_null.shape[0] if self.p_null.ndim == 3 else 1)
        self.grid = grid
        groups = grid.n_labels * grid.n_beams
        for name, table in (("p_null", self.p_null), ("mu", self.mu), ("sigma", self.sigma)):
            expected = (groups, *shape) if groups > 1 else shape
            if table.shape != expected:
                raise ParameterError(
                    f"p_reg: table {name} has shape {table.shape}; expected {expected} "
                    f"({grid.n_labels} label(s) x {grid.n_beams} beam(s) of incidence x range nodes)"
                )
        check_table("p_reg", "range_nodes", self.range_nodes, increasing=True)
        check_table("p_reg", "incidence_nodes", self.incidence_nodes, increasing=True)
        check_table("p_reg", "p_null", self.p_null, lower=0.0, upper=1.0)
        check_table("p_reg", "mu", self.mu)
        check_table("p_reg", "sigma", self.sigma, lower=1e-9)
        self._tables = {k: _f(getattr(self, k)) for k in ("p_null", "mu", "sigma")}
        self._r, self._d = _f(self.range_nodes), _f(self.incidence_nodes)
        self.groups = groups

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
        return cls(**tables, **params, grid=grid)

    # ------------------------------------------------------------------ interpolation
    def _locate(self, nodes: mi.Float, count: int, x: mi.Float):
        """Index of the node interval holding ``x`` (clamped) and the fraction within it."""
        i = dr.minimum(dr.binary_search(0, count - 1, lambda k: dr.gather(mi.Float, nodes, k + 1) <= x), count - 2)
        x0, x1 = dr.gather(mi.Float, nodes, i), dr.gather(mi.Float, nodes, i + 1)
        return i, dr.clip((x - x0) / (x1 - x0), 0.0, 1.0)

    def values(self, seg: Segment, rays: RayBatch) -> tuple[mi.Float, mi.Float, mi.Float]:
        """``(P_null, mu, sigma)`` of each lane, bilinear in (range, incidence); range only when unknown; from
        the tables of the lane's group (label and beam, as :attr:`grid` counts them)."""
        n_r, n_d = self.range_nodes.size, self.incidence_nodes.size
        i, t = self._locate(self._r, n_r, seg.nominal)
        delta = incidence_deg(seg.cos_incidence)
        j, s = self._locate(self._d, n_d, delta)
        unknown = dr.isnan(seg.cos_incidence)
        j = dr.select(unknown, n_d, j)
        s = dr.select(unknown, 0.0, s)
        j1 = dr.select(unknown, n_d, j + 1)
        group = self.grid.index(seg.nominal, seg.cos_incidence, rays.beam, seg.label) if self.groups > 1 else 0
        base = group * (n_d + 1) * n_r

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
        seg = seg.with_(
            drop=dr.select(seg.kind != ELLIPSOID, 1.0 - (1.0 - seg.drop) * (1.0 - null), seg.drop),
            mean=dr.select(surface, seg.mean + mu, seg.mean),
            sigma=dr.select(surface, sigma, seg.sigma),
        )
        if not self._gaussian_escape:
            return seg
        return seg.with_(
            mean=dr.select(escape, self["escape_mean"], seg.mean),
            sigma=dr.select(escape, self["escape_sigma"], seg.sigma),
        )

    @property
    def _gaussian_escape(self) -> bool:
        return self.choices["escape"] == "gaussian"

    def log_prob(self, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
        return log_density(seg, z) if self._gaussian_escape else super().log_prob(seg, z, rays)

    def sample(self, seg: Segment, u: mi.Point2f, rays: RayBatch) -> mi.Float:
        return sample_range(seg, u.x) if self._gaussian_escape else super().sample(seg, u, rays)

    def window(self, seg: Segment, a: float, b: float, rays: RayBatch) -> mi.Float:
        return window_probability(seg, a, b) if self._gaussian_escape else super().window(seg, a, b, rays)

    def escape(self, rays: RayBatch) -> Segment:
        return escape_segment(rays, sigma=1.0)


# ---------------------------------------------------------------------- fitting
def _node_moments(x: np.ndarray, features: np.ndarray, nodes: list[np.ndarray], bandwidths: list[float]) -> np.ndarray:
    """``sum_i k(x_i - g) f_i`` for every feature row of ``features`` (F, N) at every node ``g`` of the
    product grid of ``nodes`` (one or two dimensions; Gaussian kernel, separable): (F, G)."""
    kernels = [
        np.exp(-0.5 * ((x[:, k][None, :] - n[:, None]) / h) ** 2) for k, (n, h) in enumerate(zip(nodes, bandwidths))
    ]
    if len(kernels) == 1:
        return features @ kernels[0].T
    return np.einsum("fn,an,bn->fab", features, kernels[0], kernels[1], optimize=True).reshape(len(features), -1)


def _local_linear(
    x: np.ndarray,
    y: np.ndarray,
    w: np.ndarray,
    nodes: list[np.ndarray],
    bandwidths: list[float],
    y2: np.ndarray | None = None,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Local linear kernel regression of ``y`` on ``x`` (N, D) with sample weights ``w``, at a node grid.

    At every node the weighted least-squares line (all nodes at once, from kernel-weighted moments)
    gives the estimate; the scatter about that line, ``sum k (y2 - 2 y line + line^2) / sum k``, is
    the local variance, never negative (the difference of two separately regressed moments went
    negative at sparse nodes and collapsed sigma to its floor). Two guards keep nodes beyond the data
    sane: the line is followed at most :data:`REACH` weighted standard deviations from its data's
    weighted mean, and no estimate leaves the range of the responses (a slope extrapolated to a far
    node once gave a mean of -21 m). Every node is then shrunk to ``prior`` with the weight of
    :data:`PSEUDO_SAMPLES` samples: the estimate arithmetically, the variance geometrically (its log;
    variances floored at ``MIN_SIGMA**2``), as a scale should be.

    Args:
        x, y, w: (N, D) states, (N,) responses and (N,) weights (binned samples: cell means and counts).
        nodes, bandwidths: the node coordinates per dimension (D of them) and the kernel's bandwidths.
        y2: (N,) mean of the squared response per sample (its cell); default ``y ** 2``.
        prior: (mean, variance) at the nodes, each of the grid's shape; default: the global ones.

    Returns:
        (estimate, local variance), each of the grid's shape (product of the node counts).
    """
    y2 = y * y if y2 is None else y2
    shape, dims = tuple(len(n) for n in nodes), len(nodes)
    if prior is None:
        total = float(w.sum())
        global_mean = float(np.dot(w, y)) / total if total > 0 else 0.0
        global_variance = max(float(np.dot(w, y2)) / total - global_mean**2, 0.0) if total > 0 else 0.0
        prior = (np.full(shape, global_mean), np.full(shape, global_variance))
    if len(y) == 0:
        return prior[0].copy(), prior[1].copy()
    pairs = [(k, m) for k in range(dims) for m in range(k, dims)]
    features = [np.ones_like(y), *x.T, *(x[:, k] * x[:, m] for k, m in pairs), y, *(y * x.T), y2]
    moment = _node_moments(x, np.stack(features) * w, nodes, bandwidths)
    s0, mx, my, my2 = moment[0], moment[1 : 1 + dims].T, moment[1 + dims + len(pairs)], moment[-1]
    myx = moment[2 + dims + len(pairs) : -1].T
    mxx = np.empty((len(s0), dims, dims))
    for j, (k, m) in enumerate(pairs):
        mxx[:, k, m] = mxx[:, m, k] = moment[1 + dims + j]
    # moments about each node g (u = x - g) and the normal equations of the line c0 + c . u
    g = np.stack(np.meshgrid(*nodes, indexing="ij"), axis=-1).reshape(-1, dims)
    s1 = mx - g * s0[:, None]
    s2 = (
        mxx
        - g[:, :, None] * mx[:, None, :]
        - mx[:, :, None] * g[:, None, :]
        + g[:, :, None] * g[:, None, :] * s0[:, None, None]
    )
    syu = myx - g * my[:, None]
    live = s0 >= 1e-9
    a = np.empty((len(s0), dims + 1, dims + 1))
    a[:, 0, 0], a[:, 0, 1:], a[:, 1:, 0], a[:, 1:, 1:] = s0, s1, s1, s2
    a[~live] = np.eye(dims + 1)
    a += 1e-9 * np.maximum(s0, 1e-9)[:, None, None] * np.eye(dims + 1)
    coef = np.linalg.solve(a, np.concatenate([my[:, None], syu], axis=1)[:, :, None])[:, :, 0]
    c0, c = coef[:, 0], coef[:, 1:]
    safe = np.where(live, s0, 1.0)
    scatter = my2 - 2 * (c0 * my + np.sum(c * syu, 1)) + c0 * c0 * s0 + 2 * c0 * np.sum(c * s1, 1)
    local_variance = np.maximum((scatter + np.einsum("gk,gkl,gl->g", c, s2, c)) / safe, 0.0)
    centre = mx / safe[:, None]
    spread = np.sqrt(np.maximum(np.einsum("gkk->gk", mxx) / safe[:, None] - centre**2, 0.0))
    at = np.clip(g, centre - REACH * spread, centre + REACH * spread)
    estimate = np.clip(c0 + np.sum(c * (at - g), 1), y.min(), y.max())
    weight = np.where(live, s0, 0.0)
    mean = (weight * np.where(live, estimate, 0.0) + PSEUDO_SAMPLES * prior[0].ravel()) / (weight + PSEUDO_SAMPLES)
    # a scale shrinks multiplicatively: a 1 cm wall beside 6 cm foliage keeps its 1 cm
    log_local = np.log(np.maximum(np.where(live, local_variance, 1.0), MIN_SIGMA**2))
    log_prior = np.log(np.maximum(prior[1].ravel(), MIN_SIGMA**2))
    var = np.exp((weight * log_local + PSEUDO_SAMPLES * log_prior) / (weight + PSEUDO_SAMPLES))
    return mean.reshape(shape), var.reshape(shape)


def fit_p_reg(
    samples: StateSamples,
    held_out_score: Callable[[PRegDensity], float],
    h_ranges=(0.5, 1.0, 2.0, 4.0),
    h_incidences=(5.0, 10.0, 20.0),
    escapes=("gaussian", "uniform"),
    inlier: float = 1.0,
    z_max: float = 80.0,
    range_nodes: np.ndarray | None = None,
    incidence_nodes: np.ndarray | None = None,
    n_labels: int = 1,
    n_beams: int = 1,
    progress=None,
) -> tuple[PRegDensity, list]:
    """P-Reg: local linear regressions of P_null, mu and sigma; bandwidths chosen by held-out likelihood.

    Args:
        samples: training states and measurements (:class:`StateSamples`).
        held_out_score: mean held-out NLL (nats per ray) of a candidate density (the one likelihood).
        h_ranges, h_incidences: candidate bandwidths, m and deg.
        escapes: candidate laws of an escaped beam's return (the module docstring); the bandwidths are
            chosen with the first, then the others are tried with the chosen bandwidths.
        inlier: returns within this distance of the nominal range (m) fit mu and sigma.
        z_max: largest reported range, m.
        range_nodes, incidence_nodes: tabulation nodes (default: every 0.5 m to the farthest
            nominal range, every 5 deg).
        n_labels: element labels kept apart (labels from ``n_labels - 1`` up share the last group).
            With more than one, each label's regressions are shrunk to the pooled ones (the prior of
            :func:`_local_linear`), so a label with few samples keeps the pooled law.
        n_beams: beams kept apart (beams from ``n_beams - 1`` up share the last group); each beam's
            regressions are shrunk to its label's (or the pooled ones), as a label's are to the pooled.
        progress: optional ``progress(done, total)``.

    Returns:
        The best density and the table of candidates ``(h_range, h_incidence, escape, NLL)``.
    """
    met = samples.met
    r, d, hit, e = samples.nominal[met], samples.incidence[met], samples.hit[met], samples.residual[met]
    weight = np.asarray(samples.weight, np.float64)  # (N,): what each sample counts for
    w = weight[met]
    label = np.minimum(samples.label[met], n_labels - 1)
    beam = np.minimum(samples.beam[met], n_beams - 1)
    far = float(np.nanmax(r)) if r.size else 10.0
    r_nodes = np.arange(0.0, far + 0.5, 0.5) if range_nodes is None else np.asarray(range_nodes)
    d_nodes = np.arange(0.0, 90.0 + 1e-9, 5.0) if incidence_nodes is None else np.asarray(incidence_nodes)
    known = ~np.isnan(d)
    inl = hit & (np.abs(np.nan_to_num(e, nan=np.inf)) <= inlier)
    escaped = ~met & (weight > 0)
    escape_null = float(np.average(~samples.hit[escaped], weights=weight[escaped])) if np.any(escaped) else 0.99
    returned = ~met & samples.hit
    escape_mean, escape_sigma = _escape_moments(samples.z[returned], z_max, weight[returned])
    candidates = list(itertools.product(h_ranges, h_incidences, escapes[:1]))

    def regress(chosen: np.ndarray, h_r: float, h_d: float, prior: dict | None) -> dict[str, np.ndarray]:
        """P_null, mu and sigma^2 tables (rows: incidence nodes, then unknown) of the ``chosen`` samples."""
        tables = {k: np.zeros((d_nodes.size + 1, r_nodes.size)) for k in ("p_null", "mu", "variance")}
        unknown = chosen & ~known
        if prior is None and not unknown.any():
            unknown = chosen  # no sample of unknown incidence: that row regresses on range over all
        for rows, mask, x, nodes, bws in (
            (slice(0, d_nodes.size), chosen & known, np.stack([d, r], 1), [d_nodes, r_nodes], [h_d, h_r]),
            (slice(d_nodes.size, None), unknown, r[:, None], [r_nodes], [h_r]),
        ):
            shape = tuple(len(n) for n in nodes)
            # fine bins keep the regression cheap: per bin, the mean state and the mean of each response
            xm, missed, counts, _ = _binned(x[mask], (~hit[mask]).astype(float), w[mask], nodes)
            p_null_prior = None
            if prior is not None:
                # a mix of the group's and its parent's no-return shares: in [0, 1]
                level = _level_prior(prior["p_null"][rows].reshape(shape), nodes, xm, missed, counts)
                p_null_prior = (level, np.zeros(shape))
            p_null, _ = _local_linear(xm, missed, counts, nodes, bws, prior=p_null_prior)
            xm, em, counts, e2m = _binned(x[mask & inl], e[mask & inl], w[mask & inl], nodes)
            mu_prior = None
            if prior is not None:
                mu_prior = _level_prior_moments(
                    prior["mu"][rows].reshape(shape), prior["variance"][rows].reshape(shape), nodes, xm, em, e2m, counts
                )
            mu, variance = _local_linear(xm, em, counts, nodes, bws, y2=e2m, prior=mu_prior)
            for name, values in (("p_null", p_null), ("mu", mu), ("variance", variance)):
                tables[name][rows] = values.reshape(-1, r_nodes.size)
        return tables

    def build(h_r: float, h_d: float, escape: str) -> PRegDensity:
        pooled = regress(np.ones(r.size, bool), h_r, h_d, None)
        labels = [regress(label == k, h_r, h_d, pooled) for k in range(n_labels)] if n_labels > 1 else [pooled]
        parts = [
            regress((label == k) & (beam == b), h_r, h_d, labels[k]) if n_beams > 1 else labels[k]
            for k in range(n_labels)
            for b in range(n_beams)
        ]  # the order of StateGrid.index: label-major
        tables = {k: np.stack([part[k] for part in parts]) if len(parts) > 1 else pooled[k] for k in pooled}
        return PRegDensity(
            range_nodes=r_nodes,
            incidence_nodes=d_nodes,
            p_null=np.clip(tables["p_null"], 0, 1),
            mu=tables["mu"],
            sigma=np.sqrt(np.maximum(tables["variance"], MIN_SIGMA**2)),
            grid=StateGrid(n_labels=n_labels, n_beams=n_beams),
            z_max=z_max,
            escape_null=escape_null,
            escape=escape,
            **({"escape_mean": escape_mean, "escape_sigma": escape_sigma} if escape == "gaussian" else {}),
        )

    return choose_then_vary(
        candidates, (lambda chosen: [(*chosen[:2], e) for e in escapes[1:]],), build, held_out_score, progress
    )


def _escape_moments(z: np.ndarray, z_max: float, w: np.ndarray) -> tuple[float, float]:
    """Mean and standard deviation (m) of the returns ``z`` (N,) of escaped beams, weighted by ``w`` (N,),
    shrunk to those of the uniform law on ``[0, z_max]`` with the weight of :data:`PSEUDO_SAMPLES` returns
    (pooled second moments)."""
    n = float(np.sum(w))
    prior_mean, prior_var = z_max / 2.0, z_max**2 / 12.0
    mean = (np.sum(z * w) + PSEUDO_SAMPLES * prior_mean) / (n + PSEUDO_SAMPLES)
    second = (np.sum(z**2 * w) + PSEUDO_SAMPLES * (prior_var + prior_mean**2)) / (n + PSEUDO_SAMPLES)
    return float(mean), float(np.sqrt(max(second - mean**2, MIN_SIGMA**2)))


def _at_nodes(table: np.ndarray, nodes: list[np.ndarray], x: np.ndarray) -> np.ndarray:
    """``table`` (on the product grid of ``nodes``) interpolated (multi-)linearly at ``x`` (N, D), clamped
    to the grid, as :meth:`PRegDensity.values` reads it."""
    from scipy.interpolate import RegularGridInterpolator  # only when fitting: importing mi_lidar stays light

    return RegularGridInterpolator(nodes, table)(np.clip(x, [n[0] for n in nodes], [n[-1] for n in nodes]))


def _level_prior(prior: np.ndarray, nodes, x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """A group's prior: its own mean response, shrunk to its parent's mean at its samples with
    :data:`PSEUDO_SAMPLES` samples, flat over the nodes.

    A group (a label, or a beam within its label) is shrunk node by node to this level rather than to
    its parent's law: a label whose returns drop 95 % of the time where the pooled law drops 10 % keeps
    about 95 % where its samples are thin, and the pooled law's shape over range, which comes from the
    mix of labels at each range, is not imposed on a label that does not share it (measured on the real
    Ouster and VLP-16 frames: lower held-out NLL than the parent's shape moved to the group's level).

    Args:
        prior: the parent's table on the grid of ``nodes``.
        x, y, w: the group's binned states (N, D), responses (N,) and weights (N,).
    """
    if len(y) == 0:
        return prior
    n, parent = float(w.sum()), float(np.dot(w, _at_nodes(prior, nodes, x)))
    return np.full_like(prior, (float(np.dot(w, y)) + PSEUDO_SAMPLES * parent / n) / (n + PSEUDO_SAMPLES))


def _level_prior_moments(mu, variance, nodes, x, y, y2, w) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) priors of a group: its level as :func:`_level_prior`, its parent's variance
    scaled by the shrunk log ratio of the group's squared deviations about that level to the parent's
    variance at the same states (a ratio of sums: the log of each bin's few samples would be biased)."""
    if len(y) == 0:
        return mu, variance
    mean = _level_prior(mu, nodes, x, y, w)
    level, n = float(mean.flat[0]), float(w.sum())  # the level is flat over the nodes
    spread = float(np.dot(w, y2 - 2.0 * y * level + level * level))
    parent = float(np.dot(w, _at_nodes(variance, nodes, x)))
    ratio = math.log(max(spread, n * MIN_SIGMA**2) / max(parent, n * MIN_SIGMA**2))
    return mean, variance * math.exp(ratio * n / (n + PSEUDO_SAMPLES))


def _binned(
    x: np.ndarray, y: np.ndarray, w: np.ndarray, nodes: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Aggregate samples (states ``x`` (N, D), responses ``y`` (N,), weights ``w`` (N,)) into cells of half the
    node spacing: weighted cell means of x and y, the cells' summed weights, weighted cell means of y^2."""
    x, y, w = x[w > 0], y[w > 0], w[w > 0]
    if len(x) == 0:
        return np.zeros((0, len(nodes))), np.zeros(0), np.zeros(0), np.zeros(0)
    steps = [max(float(np.median(np.diff(n))) / 2.0, 1e-6) if n.size > 1 else 1.0 for n in nodes]
    keys = np.stack([np.floor(x[:, k] / steps[k]) for k in range(len(nodes))], 1).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    counts = np.bincount(inverse, w)
    xm = np.stack([np.bincount(inverse, x[:, k] * w) / counts for k in range(len(nodes))], 1)
    return xm, np.bincount(inverse, y * w) / counts, counts, np.bincount(inverse, y * y * w) / counts
