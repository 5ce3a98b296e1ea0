"""NP-Reg (thesis ch. 3.4): per-state histograms of the range residual, smoothed across states.

The state of a segment is its bin of a :class:`~mi_lidar.core.densities.tables.StateGrid` (nominal
range, incidence, beam, label); every state holds a histogram of the residual ``e = z - r`` on
variable-width bins (1 cm near the surface, up to 1 m far from it) and a probability ``p_null`` that
an intercepted beam gives no return. A beam that meets nothing uses the *escape* state: a histogram
of the measured range itself and the probability of a miss. A fraction ``uniform`` of the return
mass is spread over ``[0, z_max]`` (a floor: no return is impossible).

A reported range lies in ``[0, z_max]``: the residual shape of a segment is truncated there and
renormalised (the part of a smoothed histogram below ``e = -r``, or beyond ``e = z_max - r``, borrowed
from other states, is given back to the reachable bins), in :meth:`~NPRegDensity.log_prob` and
:meth:`~NPRegDensity.sample` alike, so that a sampled scan has the misses the likelihood predicts and no
return farther than the sensor reports. The fit sets ``z_max`` from the training returns
(:func:`fit_np_reg`): without it, the long tail that the smoothing shares across states (a door seen
open at 2 m, +20 m) would draw returns at 60 m from a wall at 40 m in a building whose sensor never
reported beyond 25 m.
The effects' Gaussian spread on top of a polygon may still reach below 0 by about ``seg.sigma``: such
a draw is not reported (the sensor model's blind zone).

Shapes: ``histogram`` (piecewise constant in ``e``; the binned baseline M3 of the real-planar
protocol) and ``polygon`` (the frequency polygon: linear between bin centres, which is smooth in the
location, so that effects that shift or spread the range, such as a bias or range noise, are fitted
on top of it; their Gaussian spread ``seg.sigma`` blurs the polygon by 5-point Gauss-Hermite
quadrature).

Fitting is closed form (:func:`fit_np_reg`): counts per state and bin, smoothed across states by a
Gaussian kernel ``W`` (prediction ``H W``, the thesis's estimator) whose range and incidence bandwidths
are chosen by held-out likelihood from a candidate set; :func:`fit_binned_histogram` is the fixed
smoothing of the protocol's M3.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.densities.base import ESCAPE, ReturnDensity, escape_segment, register_density, uniform_window
from mi_lidar.core.densities.samples import StateSamples, choose_then_vary, protocol_residual_edges
from mi_lidar.core.densities.tables import PSEUDO_SAMPLES, StateGrid, check_table
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import ELLIPSOID, Segment, is_open, log_density, sample_range, window_probability

# 5-point Gauss-Hermite rule for E[f(e + sqrt(2) sigma x)], weights normalised by sqrt(pi)
GH_NODES = (0.0, 0.958572464613819, -0.958572464613819, 2.020182870456086, -2.020182870456086)
GH_WEIGHTS = (0.5333333333333333, 0.2220759220056126, 0.2220759220056126, 0.0112574113277207, 0.0112574113277207)
MAX_NULL = 1.0 - 1e-6  # the largest P(no return) of a state
MAX_CUT = 1.0 - 1e-6  # at most this share of a shape is cut at z = 0 (a state that lies wholly below keeps a sliver)


def _f(values) -> mi.Float:
    return mi.Float(aligned(np.asarray(values, np.float32).ravel()))


@register_density
class NPRegDensity(ReturnDensity):
    """Nonparametric return density: a residual histogram per state (see the module docstring).

    Build it with :func:`fit_np_reg` (or ``mi-lidar fit-sensor --model np-reg``) and reference its
    file from XML: ``<string name="density" value="np_reg(file=sensor.npz)"/>``. Ellipsoid elements
    keep their own Gaussian.
    """

    name = "np_reg"
    learned = True
    options = {"shape": ("polygon", "histogram")}
    specs = {
        "uniform": ParamSpec(
            1e-3, "1", "share of the return mass spread uniformly on [0, z_max]", lower=0.0, upper=1.0, fit=False
        ),
        "z_max": ParamSpec(80.0, "m", "largest range the sensor reports", lower=1e-3, upper=1e4, fit=False),
    }

    def __init__(
        self,
        grid: StateGrid | None = None,
        edges: np.ndarray | None = None,
        mass: np.ndarray | None = None,
        p_null: np.ndarray | None = None,
        **values,
    ):
        super().__init__(**values)
        self.grid = grid or StateGrid()
        self.edges = np.asarray(protocol_residual_edges() if edges is None else edges, np.float64)
        n_bins, n_states = self.edges.size - 1, self.grid.size + 1
        centre = np.argmin(np.abs(0.5 * (self.edges[1:] + self.edges[:-1])))
        default = np.zeros((n_states, n_bins))
        default[:, centre] = 1.0
        self.mass = np.asarray(default if mass is None else mass, np.float64)
        self.p_null = np.asarray(np.zeros(n_states) if p_null is None else p_null, np.float64)
        if self.mass.shape != (n_states, n_bins) or self.p_null.shape != (n_states,):
            raise ParameterError(
                f"np_reg: tables of shapes {self.mass.shape} and {self.p_null.shape} for {n_states} states "
                f"(grid + escape) and {n_bins} bins"
            )
        check_table("np_reg", "edges", self.edges, increasing=True)
        check_table("np_reg", "mass", self.mass, lower=0.0)
        check_table("np_reg", "p_null", self.p_null, lower=0.0, upper=1.0)
        self._upload()

    # ------------------------------------------------------------------ tables
    def _upload(self) -> None:
        """Normalise the tables and hand them to Dr.Jit (densities, polygon norms, sampling CDFs)."""
        edges, mass = self.edges, np.clip(self.mass, 0.0, None)
        total = mass.sum(axis=1, keepdims=True)
        mass = np.where(total > 0, mass / np.maximum(total, 1e-300), 1.0 / mass.shape[1])
        width = np.diff(edges)
        density = mass / width
        centres = 0.5 * (edges[1:] + edges[:-1])
        segment = 0.5 * (density[:, 1:] + density[:, :-1]) * np.diff(centres)  # polygon mass between centres
        norm = np.maximum(segment.sum(axis=1), 1e-300)
        self._b = width.size
        self._edges, self._width, self._centres = _f(edges), _f(width), _f(centres)
        self._density, self._norm = _f(density), _f(norm)
        self._cdf_hist = _f(np.cumsum(mass, axis=1))
        self._cdf_poly = _f(np.cumsum(segment / norm[:, None], axis=1))
        self._p_null = _f(self.p_null)

    def tables(self) -> dict[str, np.ndarray]:
        """The arrays saved to a density file."""
        return {"edges": self.edges, "mass": self.mass, "p_null": self.p_null}

    @classmethod
    def from_tables(cls, params: dict, grid: StateGrid | None, tables: dict[str, np.ndarray]) -> NPRegDensity:
        return cls(grid=grid, edges=tables["edges"], mass=tables["mass"], p_null=tables["p_null"], **params)

    # ------------------------------------------------------------------ state and lookup
    def state(self, seg: Segment, rays: RayBatch) -> mi.UInt32:
        """Flat state index of each lane (the escape state for ``kind == ESCAPE``)."""
        inner = self.grid.index(seg.nominal, seg.cos_incidence, rays.beam, seg.label)
        return dr.select(seg.kind == ESCAPE, self.grid.size, inner)

    def _residual(self, seg: Segment, z: mi.Float) -> mi.Float:
        return z - dr.select(seg.kind == ESCAPE, 0.0, seg.mean)

    def _shape_density(self, state: mi.UInt32, e: mi.Float) -> mi.Float:
        """Density (1/m) of residual ``e`` under the state's histogram or polygon (0 outside the support)."""
        b = self._b
        if self.choices["shape"] == "histogram":
            k = dr.binary_search(0, b, lambda i: dr.gather(mi.Float, self._edges, i + 1) <= e)
            k = dr.minimum(k, b - 1)
            inside = (e >= dr.gather(mi.Float, self._edges, 0)) & (e < dr.gather(mi.Float, self._edges, b))
            return dr.select(inside, dr.gather(mi.Float, self._density, state * b + k), 0.0)
        j = dr.minimum(dr.binary_search(0, b - 1, lambda i: dr.gather(mi.Float, self._centres, i + 1) <= e), b - 2)
        c0, c1 = dr.gather(mi.Float, self._centres, j), dr.gather(mi.Float, self._centres, j + 1)
        d0, d1 = (
            dr.gather(mi.Float, self._density, state * b + j),
            dr.gather(mi.Float, self._density, state * b + j + 1),
        )
        t = dr.clip((e - c0) / (c1 - c0), 0.0, 1.0)
        inside = (e >= dr.gather(mi.Float, self._centres, 0)) & (e <= dr.gather(mi.Float, self._centres, b - 1))
        return dr.select(inside, (d0 + t * (d1 - d0)) / dr.gather(mi.Float, self._norm, state), 0.0)

    def _polygon_piece(self, state: mi.UInt32, j: mi.UInt32) -> tuple[mi.Float, mi.Float, mi.Float, mi.Float]:
        """Piece ``j`` of the state's polygon: the bin centres it joins (m) and its normalised densities there (1/m)."""
        b = self._b
        norm = dr.gather(mi.Float, self._norm, state)
        return (
            dr.gather(mi.Float, self._centres, j),
            dr.gather(mi.Float, self._centres, j + 1),
            dr.gather(mi.Float, self._density, state * b + j) / norm,
            dr.gather(mi.Float, self._density, state * b + j + 1) / norm,
        )

    def _shape_cdf(self, state: mi.UInt32, e: mi.Float) -> mi.Float:
        """Mass of the state's histogram or polygon below residual ``e`` (0 below the support, 1 above)."""
        b = self._b
        if self.choices["shape"] == "histogram":
            k = dr.minimum(dr.binary_search(0, b, lambda i: dr.gather(mi.Float, self._edges, i + 1) <= e), b - 1)
            before = dr.select(k > 0, dr.gather(mi.Float, self._cdf_hist, state * b + k - 1), 0.0)
            mass = dr.gather(mi.Float, self._cdf_hist, state * b + k) - before
            frac = dr.clip((e - dr.gather(mi.Float, self._edges, k)) / dr.gather(mi.Float, self._width, k), 0.0, 1.0)
            return before + frac * mass
        m = b - 1
        j = dr.minimum(dr.binary_search(0, m, lambda i: dr.gather(mi.Float, self._centres, i + 1) <= e), m - 1)
        before = dr.select(j > 0, dr.gather(mi.Float, self._cdf_poly, state * m + j - 1), 0.0)
        c0, c1, d0, d1 = self._polygon_piece(state, j)
        t = dr.clip(e - c0, 0.0, c1 - c0)
        return dr.clip(before + d0 * t + 0.5 * (d1 - d0) / (c1 - c0) * t * t, 0.0, 1.0)

    def _truncation(self, seg: Segment, state: mi.UInt32) -> tuple[mi.Float, mi.Float]:
        """Mass of each lane's shape below range 0, and the mass it keeps on ``[0, z_max]`` (at least
        ``1 - MAX_CUT``): what the truncation removes below, and its normaliser."""
        below = dr.minimum(self._shape_cdf(state, self._residual(seg, dr.zeros(mi.Float, dr.width(state)))), MAX_CUT)
        reach = self._shape_cdf(state, self._residual(seg, self["z_max"]))
        return below, dr.maximum(reach - below, 1.0 - MAX_CUT)

    # ------------------------------------------------------------------ density interface
    def prepare(self, seg: Segment, rays: RayBatch) -> Segment:
        surface = seg.kind != ELLIPSOID
        null = dr.gather(mi.Float, self._p_null, self.state(seg, rays))
        return seg.with_(
            drop=dr.select(surface, 1.0 - (1.0 - seg.drop) * (1.0 - null), seg.drop),
            sigma=dr.select(surface, 0.0, seg.sigma),
        )

    def escape(self, rays: RayBatch) -> Segment:
        return escape_segment(rays)  # prepare() gives it the escape state's P(null), as to any segment

    def log_prob(self, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
        state = self.state(seg, rays)
        e = self._residual(seg, z)
        if self.choices["shape"] == "polygon":
            spread = math.sqrt(2.0) * seg.sigma
            shape = sum(w * self._shape_density(state, e - spread * x) for x, w in zip(GH_NODES, GH_WEIGHTS))
        else:
            shape = self._shape_density(state, e)
        u = self["uniform"]
        z_max = self["z_max"]
        inside = (z >= 0) & (z <= z_max)
        floor = dr.select(inside, u / z_max, 0.0)
        shape = dr.select(inside, shape / self._truncation(seg, state)[1], 0.0)
        value = dr.log(dr.maximum((1.0 - u) * shape + floor, 1e-30))
        return dr.select(seg.kind == ELLIPSOID, log_density(seg, z), value)

    def window(self, seg: Segment, a: float, b: float, rays: RayBatch) -> mi.Float:
        if is_open(a, b):  # the shapes are truncated and the floor lies on [0, z_max]
            return dr.select(seg.kind == ELLIPSOID, window_probability(seg, a, b), 1.0)
        state = self.state(seg, rays)
        low, high = self._residual(seg, max(a, 0.0)), self._residual(seg, dr.minimum(b, self["z_max"]))
        if self.choices["shape"] == "polygon":
            spread = math.sqrt(2.0) * seg.sigma
            nodes = list(zip(GH_NODES, GH_WEIGHTS))
            part = sum(
                w * (self._shape_cdf(state, high - spread * x) - self._shape_cdf(state, low - spread * x))
                for x, w in nodes
            )
        else:
            part = self._shape_cdf(state, high) - self._shape_cdf(state, low)
        shape = dr.clip(part / self._truncation(seg, state)[1], 0.0, 1.0)
        u = self["uniform"]
        mixed = dr.clip((1.0 - u) * shape + u * uniform_window(self["z_max"], a, b), 0.0, 1.0)
        return dr.select(seg.kind == ELLIPSOID, window_probability(seg, a, b), mixed)

    def sample(self, seg: Segment, u: mi.Point2f, rays: RayBatch) -> mi.Float:
        state = self.state(seg, rays)
        share = self["uniform"]
        floor = u.x < share
        v = dr.clip((u.x - share) / (1.0 - share), 0.0, 1.0 - 1e-7)
        below, kept = self._truncation(seg, state)
        v = dr.minimum(below + v * kept, 1.0 - 1e-7)  # the shape truncated to [0, z_max]
        b = self._b
        if self.choices["shape"] == "histogram":
            k = dr.minimum(
                dr.binary_search(0, b, lambda i: dr.gather(mi.Float, self._cdf_hist, state * b + i) <= v), b - 1
            )
            before = dr.select(k > 0, dr.gather(mi.Float, self._cdf_hist, state * b + k - 1), 0.0)
            mass = dr.gather(mi.Float, self._cdf_hist, state * b + k) - before
            frac = dr.clip((v - before) / dr.maximum(mass, 1e-12), 0.0, 1.0)
            e = dr.gather(mi.Float, self._edges, k) + frac * dr.gather(mi.Float, self._width, k)
        else:
            m = b - 1
            j = dr.minimum(
                dr.binary_search(0, m, lambda i: dr.gather(mi.Float, self._cdf_poly, state * m + i) <= v), m - 1
            )
            before = dr.select(j > 0, dr.gather(mi.Float, self._cdf_poly, state * m + j - 1), 0.0)
            c0, c1, d0, d1 = self._polygon_piece(state, j)
            length, target = c1 - c0, (v - before)
            slope = (d1 - d0) / length
            # invert d0 t + slope t^2 / 2 = target on [0, length]
            root = dr.sqrt(dr.maximum(d0 * d0 + 2.0 * slope * target, 0.0))
            t = dr.select(dr.abs(slope) > 1e-6 * (d0 + d1 + 1e-12), (root - d0) / slope, target / dr.maximum(d0, 1e-12))
            e = c0 + dr.clip(t, 0.0, length)
        normal = math.sqrt(2.0) * dr.erfinv(dr.clip(2.0 * u.y - 1.0, -1.0 + 1e-7, 1.0 - 1e-7))
        z = dr.select(seg.kind == ESCAPE, 0.0, seg.mean) + e + seg.sigma * normal
        z = dr.select(floor, u.x / dr.maximum(share, 1e-12) * self["z_max"], z)
        return dr.select(seg.kind == ELLIPSOID, sample_range(seg, u.x), z)


# ---------------------------------------------------------------------- fitting
def count_states(samples: StateSamples, grid: StateGrid, edges: np.ndarray) -> np.ndarray:
    """(S + 1, B + 1) counts per state (escape last) of residual bins, with the no-returns in the last column;
    each sample counts its weight (``samples.weight``, e.g. a share of an outcome,
    :meth:`~mi_lidar.core.likelihood.ElementShares.posterior`)."""
    n_states, n_bins = grid.size + 1, edges.size - 1
    state = np.full(samples.n, grid.size, np.int64)
    met = samples.met
    state[met] = grid.index_np(samples.nominal[met], samples.incidence[met], samples.beam[met], samples.label[met])
    e = np.where(met, samples.z - np.where(met, samples.nominal, 0.0), samples.z)
    k = np.searchsorted(edges, e, side="right") - 1
    ok = samples.hit & (k >= 0) & (k < n_bins)
    weight = np.asarray(samples.weight, np.float64)
    counts = np.zeros((n_states, n_bins + 1))
    np.add.at(counts, (state[ok], k[ok]), weight[ok])
    np.add.at(counts, (state[~samples.hit], n_bins), weight[~samples.hit])
    return counts


def _finish(counts: np.ndarray, e_kernel: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mass, p_null) from smoothed counts (escape state last); ``e_kernel``: [1/4 1/2 1/4] along the residual.

    A state without data gets P(null) 0.5, except the escape state: a beam that met nothing, in a log
    where no such beam was seen, reports nothing (P(null) = 1 - 1e-6).
    """
    hist, null = counts[:, :-1], counts[:, -1]
    if e_kernel:
        padded = np.pad(hist, ((0, 0), (1, 1)), mode="edge")
        hist = 0.25 * padded[:, :-2] + 0.5 * padded[:, 1:-1] + 0.25 * padded[:, 2:]
    total = hist.sum(axis=1) + null
    p_null = np.where(total > 0, null / np.maximum(total, 1e-300), 0.5)
    if total[-1] <= 0:
        p_null[-1] = 1.0
    return hist, np.clip(p_null, 0.0, MAX_NULL)


def fit_binned_histogram(
    samples: StateSamples,
    grid: StateGrid,
    edges: np.ndarray | None = None,
    neighbour: float = 0.5,
    pseudo: float = PSEUDO_SAMPLES,
    uniform: float = 1e-3,
    z_max: float = 80.0,
) -> NPRegDensity:
    """The real-planar protocol's M3: per-bin histograms with its fixed smoothing.

    Counts are smoothed over neighbouring range and incidence bins (weight ``neighbour``; the
    unknown-incidence bin and the escape state have no incidence neighbours), shrunk towards the
    global histogram with ``pseudo`` pseudo-beams, and smoothed by [1/4 1/2 1/4] along the residual;
    ``uniform`` of the mass is spread over ``[0, z_max]``.
    """
    edges = protocol_residual_edges(z_max) if edges is None else np.asarray(edges)
    counts = count_states(samples, grid, edges)
    inner = counts[:-1].reshape(-1, grid.n_incidence, grid.n_range, counts.shape[1])  # (beam*label, inc, range, b)
    smooth = inner.copy()
    smooth[:, :, 1:] += neighbour * inner[:, :, :-1]
    smooth[:, :, :-1] += neighbour * inner[:, :, 1:]
    known = grid.n_incidence - 1 if grid.incidence_edges else 0
    if known > 1:
        smooth[:, 1:known] += neighbour * inner[:, : known - 1]
        smooth[:, : known - 1] += neighbour * inner[:, 1:known]
    smooth = smooth.reshape(-1, counts.shape[1])
    overall = smooth.sum(axis=0)
    overall = overall / max(overall.sum(), 1e-300)
    counts = np.concatenate([smooth + pseudo * overall, counts[-1:]])
    mass, p_null = _finish(counts, e_kernel=True)
    return NPRegDensity(
        grid=grid, edges=edges, mass=mass, p_null=p_null, shape="histogram", uniform=uniform, z_max=z_max
    )


def kernel_smooth(
    grid: StateGrid, counts: np.ndarray, h_range: float, h_incidence: float, h_null: float | None = None
) -> np.ndarray:
    """``W @ counts``: (S, B + 1) per-state counts (no-returns last) smoothed across states by a Gaussian kernel ``W``.

    ``W`` weighs states by their centres' distance in range (m, bandwidth ``h_range``) and incidence
    (deg, ``h_incidence``); beams and labels stay apart, and the unknown-incidence bin only mixes with
    itself (across ranges).

    ``h_null`` (m; default ``h_range``): the range bandwidth of P(no return) alone, which may change with range
    faster than the residual's shape. P(no return) is then the kernel estimate ``(W' n) / (W' t)`` (``n`` a
    state's no-returns, ``t`` all its outcomes, ``W'`` the kernel with ``h_null``), set back as a count
    against the state's smoothed returns. With one kernel for both, the far states, which hold few beams,
    borrowed their P(no return) from the many nearer ones (Freiburg 101, h 4 m: beams whose first wall lay
    past 30 m were predicted to miss 50 % of the time where 59 % of the training beams did, and those nearer than
    2.4 m 4.7 % where 3.8 % did).
    """
    smoothed = _kernel_product(grid, counts, h_range, h_incidence)
    if h_null is None or h_null == h_range:
        return smoothed
    outcomes = np.stack([counts[:, -1], counts.sum(axis=1)], axis=1)
    null, total = _kernel_product(grid, outcomes, h_null, h_incidence).T
    returns = smoothed[:, :-1].sum(axis=1)
    known = (total > 0) & (returns > 0)
    p_null = np.minimum(np.divide(null, total, out=np.zeros_like(null), where=known), MAX_NULL)
    smoothed[known, -1] = returns[known] * p_null[known] / (1.0 - p_null[known])
    return smoothed


def _kernel_product(grid: StateGrid, counts: np.ndarray, h_range: float, h_incidence: float) -> np.ndarray:
    """``W @ counts`` of :func:`kernel_smooth`. The kernel is a product of a range and an incidence factor, so
    it is applied as two small products along those axes of the (beam x label, incidence, range, B) counts
    rather than as the dense (S, S) matrix (which took seconds on a fine grid)."""
    r = grid.range_centres
    if grid.incidence_edges:
        inc_edges = np.asarray(grid.incidence_edges, np.float64)
        inc = np.concatenate([0.5 * (inc_edges[:-1] + inc_edges[1:]), [np.nan]])
    else:
        inc = np.array([0.0])
    dr_ = (r[:, None] - r[None, :]) / max(h_range, 1e-9)
    w_r = np.exp(-0.5 * dr_**2)
    di = (inc[:, None] - inc[None, :]) / max(h_incidence, 1e-9)
    w_i = np.where(np.isnan(di), 0.0, np.exp(-0.5 * np.nan_to_num(di) ** 2))
    unknown = np.isnan(inc)
    w_i[np.ix_(unknown, unknown)] = 1.0
    blocks = counts.reshape(-1, grid.n_incidence, grid.n_range, counts.shape[-1])  # StateGrid.index ordering
    smoothed = np.einsum("rs,gisb->girb", w_r, blocks)
    smoothed = np.einsum("ij,gjrb->girb", w_i, smoothed)
    return smoothed.reshape(counts.shape)


def shrink_beams(grid: StateGrid, counts: np.ndarray, pseudo: float = PSEUDO_SAMPLES) -> np.ndarray:
    """Per-beam counts (S, B + 1) shrunk, in place, to their label's: each beam's state gains ``pseudo``
    samples distributed as the sum over its label's beams at the same range and incidence (no-returns
    included).

    A beam with few samples at a state thus keeps its label's law there; with beams pooled
    (``grid.n_beams == 1``) the counts are returned unchanged.
    """
    if grid.n_beams == 1:
        return counts
    blocks = counts.reshape(grid.n_labels, grid.n_beams, -1, counts.shape[-1])  # StateGrid.index ordering
    parent = blocks.sum(axis=1, keepdims=True)
    total = parent.sum(axis=-1, keepdims=True)
    share = np.divide(parent, total, out=np.zeros_like(parent), where=total > 0)
    blocks += pseudo * share  # in place where the reshape is a view: the tables can hold tens of millions of entries
    return blocks.reshape(counts.shape)


REACHES = (1.0, 1.1, 1.25, 1.5, math.inf)  # candidate ends of the range support, in farthest training returns
NULL_BANDWIDTHS = (0.5, 1.0, 2.0, 4.0)  # m: candidate range bandwidths of P(no return) alone (kernel_smooth)


def support_end(samples: StateSamples, reach: float, z_max: float) -> float:
    """The end (m) of a learned density's range support: ``reach`` times the farthest return of ``samples``,
    at most ``z_max`` (the sensor's largest range; ``reach`` infinite, or no return: ``z_max``)."""
    returned = samples.z[samples.hit & np.isfinite(samples.z)]
    if not returned.size or not math.isfinite(reach):
        return float(z_max)
    return float(min(z_max, reach * float(returned.max())))


def fit_np_reg(
    samples: StateSamples,
    grid: StateGrid,
    held_out_score: Callable[[NPRegDensity], float],
    h_ranges=(0.5, 1.0, 2.0, 4.0),
    h_incidences=(5.0, 10.0, 20.0),
    uniforms=(1e-3,),
    reaches=REACHES,
    h_nulls=NULL_BANDWIDTHS,
    edges: np.ndarray | None = None,
    z_max: float = 80.0,
    progress=None,
) -> tuple[NPRegDensity, list]:
    """NP-Reg: per-state counts smoothed by the kernel ``W`` (``H W``), bandwidths chosen by held-out likelihood.

    With beams kept apart (``grid.n_beams > 1``) each beam's smoothed counts are shrunk to its label's
    (:func:`shrink_beams`). The bandwidths and the uniform floor are chosen first, with the support
    ending at ``z_max`` and one kernel for the returns and the no-returns; then the end of the support
    (:func:`support_end`) among ``reaches``, with the chosen bandwidths: a sensor that never reported beyond
    25 m in training is not drawn returning at 60 m, and one whose held-out returns reach farther than its
    training ones keeps a margin; then P(no return)'s own range bandwidth among ``h_nulls``
    (:func:`kernel_smooth`; one value alone is used from the start: a refit at a chosen setting).

    Args:
        samples: training states and measurements, each counted with its weight.
        grid: the state grid (fine bins; the kernel does the smoothing).
        held_out_score: mean held-out NLL (nats per ray) of a candidate density (the one likelihood).
        h_ranges, h_incidences, uniforms: candidate range bandwidths (m), incidence bandwidths
            (deg) and uniform floors.
        reaches: candidate ends of the range support, in farthest training returns (``inf``: ``z_max``).
        h_nulls: candidate range bandwidths (m) of P(no return) alone.
        edges: residual bin edges (default: the protocol's).
        z_max: largest range the sensor reports, m.
        progress: optional ``progress(done, total)``.

    Returns:
        The best density and the table of candidates ``(h_range, h_incidence, uniform, reach, h_null, NLL)``.
    """
    edges = protocol_residual_edges(z_max) if edges is None else np.asarray(edges)
    counts = count_states(samples, grid, edges)
    reaches = tuple(reaches)
    widest = max(reaches)
    h_nulls = tuple(h_nulls)
    one_null = h_nulls[0] if len(h_nulls) == 1 else None  # a refit at a chosen setting; else first one kernel
    candidates = [
        (h_r, h_i, u, widest, h_r if one_null is None else one_null)
        for h_r, h_i, u in itertools.product(h_ranges, h_incidences if grid.incidence_edges else (1.0,), uniforms)
    ]

    def build(h_r: float, h_i: float, u: float, reach: float, h_null: float) -> NPRegDensity:
        smoothed = kernel_smooth(grid, counts[:-1], h_r, h_i, h_null)
        mass, p_null = _finish(np.concatenate([shrink_beams(grid, smoothed), counts[-1:]]), e_kernel=True)
        end = support_end(samples, reach, z_max)
        return NPRegDensity(grid=grid, edges=edges, mass=mass, p_null=p_null, shape="polygon", uniform=u, z_max=end)

    def shorter(chosen: tuple) -> list:
        return [(*chosen[:3], r, chosen[4]) for r in reaches if r != widest]

    def null_bandwidth(chosen: tuple) -> list:
        return [(*chosen[:4], h) for h in h_nulls if h != chosen[4]]  # none left for a single value

    return choose_then_vary(candidates, (shorter, null_bandwidth), build, held_out_score, progress)
