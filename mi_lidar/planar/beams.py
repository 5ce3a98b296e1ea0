"""Traced planar beams as the likelihood engine sees them: elements, rounds, rays, and their scores.

A :class:`~mi_lidar.planar.trace.PlanarTrace` is turned into the engine's inputs (an element table
without geometry, compact rounds, rays) so that every model of the planar benchmark is scored by the
one likelihood and sampled by the one sampler:

* :func:`nominal_beams`: each beam meets one opaque element at its nominal range (the first occupied
  cell), or nothing (a nominal miss): the view of the protocol's models M0-M3, P-Reg and NP-Reg;
* :func:`segment_beams`: each beam meets every cell with leave-out hits along it, in order, each an
  element of its own with its counts, at the range of the cell's surface; its interception
  probability is the counting estimate with a fitted Beta prior (mi-lidar's permeable map,
  :func:`permeability`, :func:`fit_permeability`);

The beam's angular spread (its neighbours' traces mixed in) is :mod:`mi_lidar.planar.angular`.

Element labels carry the cell's occupancy (1: ``occ3`` occupied, 0: stray hits) and how much evidence
its leave-out hits give (:func:`segment_labels`), so densities can condition on them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.fitting import FitVariable, adam_fit, lookup
from mi_lidar.core.likelihood import mixture_log_likelihood, score
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.streams import BeamCorrelation, NeighbourStreams, scan_follows
from mi_lidar.core.trace import RayCache, cache_distributions, rounds_from_segments
from mi_lidar.planar.trace import BACKSTOP, OCCUPANCY_NAMES, OPEN_BACKSTOP, OPEN_STRAY, PlanarTrace

OCCUPANCY_CLASSES = len(OCCUPANCY_NAMES)  # one Beta prior per occupancy class (raymarch.BACKSTOP and the rest)
LABELS_BEYOND = OPEN_STRAY - BACKSTOP + 1  # labels after the cells' 2 * cell_labels(...) (segment_labels)
LINE_CLASSES = 2  # a cell's neighbourhood is line-like by the protocol's rule, or not (segment_labels)
INTERCEPTION_PARAMETERS = ("a", "b", "gamma", "kappa", "eta")  # per occupancy class (see permeability)
UNCOUNTED = (BACKSTOP, OPEN_BACKSTOP)  # occupancy classes without counts: their kappa stays 1 (fit_permeability)
WALLS = (1,)  # the occupancy class whose incidence is that of its own surface: only its eta is fitted
PERMEABILITY_TOLERANCE = 1e-5  # nats per beam: the Beta priors' fit has converged (see fit_permeability)
EVIDENCE_CLASSES = 5  # at most: leave-out hits of a cell 1, 2-3, 4-7, 8-15, 16 or more (doublings)


def segment_labels(
    occupied: np.ndarray, hits: np.ndarray, classes: int = EVIDENCE_CLASSES, line_like: np.ndarray | None = None
) -> np.ndarray:
    """Label of each segment: ``occupied * classes + evidence`` for a cell, evidence = log2 of its hits, capped at
    ``classes - 1``; given ``line_like`` (whether the protocol's rule finds a line in each cell's neighbourhood:
    ``seg_line_incidence`` known), ``(occupied * classes + evidence) * 2 + (not line_like)``.

    A wall seen by many scans is located to a centimetre; a cell with one or two hits (seen once,
    or a person's legs) is not, and its returns spread more: the residual law depends on both.
    ``classes = 1`` labels occupancy alone. The density's states read the incidence on each cell's surface
    (``seg_incidence``, known on more cells than the protocol's line incidence); ``line_like`` tells a cell on a
    straight wall from clutter met at the same incidence, which returns by another law (whether to tell them
    apart is chosen held out, :func:`~mi_lidar.planar.permeable.fit_milidar`).
    The classes of :meth:`~mi_lidar.planar.trace.PlanarTrace.with_backstops` (``occupied`` 2 a backstop, 3 the
    backstop of a beam in the open, 4 a stray cell on a beam in the open) have a label each, from
    ``2 * cell_labels(classes, lines)`` on: what a beam meets after passing every cell listed for it (a wall the
    map has not seen, or ground far behind a bush) returns and misses by its own law
    (:func:`~mi_lidar.planar.permeable.backstop_prior`), and a beam in the open by laws of its own
    (:data:`LABELS_BEYOND` labels).
    """
    occupied = np.asarray(occupied, np.int64)
    evidence = np.clip(np.floor(np.log2(np.maximum(hits, 1))), 0, classes - 1).astype(np.int64)
    cell = np.minimum(occupied, 1) * classes + evidence
    if line_like is not None:
        cell = cell * LINE_CLASSES + ~np.asarray(line_like, bool)
    return np.where(occupied >= BACKSTOP, 2 * cell_labels(classes, line_like is not None) + occupied - BACKSTOP, cell)


def trace_labels(trace: PlanarTrace, classes: int, lines: bool) -> np.ndarray:
    """(E,) :func:`segment_labels` of every segment of ``trace``, telling line-like cells apart with ``lines``."""
    return segment_labels(trace.seg_occupied, trace.seg_hits, classes, trace.seg_line_like if lines else None)


def cell_labels(classes: int, lines: bool) -> int:
    """The labels of the cells of one occupancy (stray-hit or ``occ3``): ``classes`` evidence classes, times
    line-like or not with ``lines`` (:func:`segment_labels`)."""
    return classes * (LINE_CLASSES if lines else 1)


def _f(values) -> mi.Float:
    return mi.Float(aligned(np.asarray(values, np.float32)))


def _cos(incidence_deg: np.ndarray) -> np.ndarray:
    """|cos| of incidence angles (deg); NaN (unknown) stays NaN."""
    return np.cos(np.radians(incidence_deg))


def base_model(density) -> SensorModel:
    """The sensor model of the planar benchmark around ``density`` (nothing else: the map is the scene).

    Its range window is open (``max_range`` infinite): the protocol scores every model on the beams'
    nominal states, and a model knows the log's no-return value only through its density's ``z_max``
    (the protocol's M0 predicts a return at every nominal hit, also beyond a clipping sensor's maximum).
    """
    return SensorModel(range_sigma=0.05, max_range=math.inf, max_segments=64, density=density)


@dataclass
class EngineBeams:
    """Beams of a planar trace in the engine's terms.

    Attributes:
        table: one element per traced segment (no geometry).
        rays: one ray per beam (beam index and ray id; no geometry needed).
        rounds: the segments of each beam, in order.
        z, hit: measured range (m; 0 for a miss) and return flag per beam.
        hits, passes: leave-out counts of every element (for :func:`permeability`).
        occupied: (E,) occupancy class of every element: 1 an ``occ3`` occupied cell, 0 stray hits,
            2-4 a backstop, the backstop and a stray cell of a beam in the open
            (:meth:`~mi_lidar.planar.trace.PlanarTrace.with_backstops`).
        ranges: (E,) the range at which the beam meets every element, m.
        cos_incidence: (E,) |cos| of the incidence at which the beam meets every element (NaN: unknown).
        follows: (B,) beam ``i`` is the next beam of beam ``i - 1``'s scan
            (:func:`~mi_lidar.core.streams.scan_follows`).
        correlation: how much neighbouring beams share their random draws when sampled
            (:class:`~mi_lidar.core.streams.BeamCorrelation`; none by default).
    """

    table: ElementTable
    rays: RayBatch
    rounds: object
    z: mi.Float
    hit: mi.Bool
    hits: np.ndarray
    passes: np.ndarray
    occupied: np.ndarray
    ranges: np.ndarray
    cos_incidence: np.ndarray
    follows: np.ndarray
    correlation: BeamCorrelation = BeamCorrelation()

    @property
    def n(self) -> int:
        return self.rays.width

    def problem(self) -> Problem:
        """These beams as a fixed :class:`~mi_lidar.core.problem.Problem` (for the one fitter)."""
        return Problem.from_rounds(self.table, self.rays, self.rounds, self.z, self.hit)

    def raw_log_likelihood(self, model) -> np.ndarray:
        """(B,) raw log-likelihood per beam (log density (1/m) of a return, log P of a miss; nats)."""
        with dr.suspend_grad():
            return np.asarray(mixture_log_likelihood(self.table, model, self.rays, self.rounds, self.z, self.hit))

    def log_likelihood(self, model) -> np.ndarray:
        """(B,) scored log-likelihood per beam (nats)."""
        return scored(self.raw_log_likelihood(model), np.asarray(self.hit))

    def p_miss(self, model) -> np.ndarray:
        """(B,) probability of no return per beam."""
        with dr.suspend_grad():
            miss = dr.full(mi.Bool, False, self.n)
            raw = mixture_log_likelihood(self.table, model, self.rays, self.rounds, dr.zeros(mi.Float, self.n), miss)
            return np.exp(np.asarray(raw, np.float64))

    def with_permeability(self, a, b, gamma, kappa, eta) -> EngineBeams:
        """These beams with every element's interception probability from its counts, range and incidence
        (:func:`permeability`).

        ``a``, ``b``, ``gamma``, ``kappa`` and ``eta`` hold one value per occupancy class (index 0: stray hits,
        1: occupied, 2: backstops, ...).
        """
        k = self.occupied
        if not self.hits.size:
            return dataclasses.replace(self, table=self.table.replaced(p_hit=_f(np.ones(1))))
        a, b, gamma, kappa, eta = (np.asarray(v)[k] for v in (a, b, gamma, kappa, eta))
        p = permeability(self.hits, self.passes, a, b, self.ranges, gamma, kappa, self.cos_incidence, eta)
        return dataclasses.replace(self, table=self.table.replaced(p_hit=_f(p)))

    @property
    def ray_id(self):
        """The rays' ids (as numbered by :meth:`numbered_from`): they key every random stream."""
        return self.rays.ray_id

    def with_correlation(self, correlation: BeamCorrelation) -> EngineBeams:
        """These beams sampled with ``correlation``."""
        return dataclasses.replace(self, correlation=correlation)

    def streams(self, seed: int, follows: np.ndarray | None = None) -> int | NeighbourStreams:
        """The random streams of a sample with ``seed``: shared by neighbouring beams per :attr:`correlation`.

        ``follows``: that of the whole set when these beams are a part of it (:meth:`numbered_from`); default
        :attr:`follows`.
        """
        follows = self.follows if follows is None else follows
        return NeighbourStreams(seed, follows, self.correlation) if self.correlation.active else seed

    def numbered_from(self, first: int) -> EngineBeams:
        """These beams as rays ``first .. first + n - 1`` of a larger set, so that they draw that set's random
        numbers (with the set's :meth:`streams`): scored and sampled part by part, a set gives what it gives
        at once."""
        rays = dataclasses.replace(self.rays, ray_id=dr.arange(mi.UInt32, first, first + self.n))
        return dataclasses.replace(self, rays=rays)

    def sample(
        self, model, seed: int | NeighbourStreams = 0, active: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sampled (range, hit) per beam, from :meth:`streams` of ``seed`` (or the streams given).

        ``active``: (B,) bool, only these beams draw (the others report a miss; each beam's draw is the same
        as in a draw of every beam)."""
        streams = seed if isinstance(seed, NeighbourStreams) else self.streams(seed)
        with dr.suspend_grad():
            lanes = None if active is None else mi.Bool(aligned(np.asarray(active, bool)))
            z, hit = model.sample_trace(self.table, self.rays, self.rounds, streams, lanes)
            return np.asarray(z, np.float64), np.asarray(hit)


def scored(raw: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """(B,) the one score (:func:`~mi_lidar.core.likelihood.score`) of raw per-beam log-likelihoods, as float64."""
    with dr.suspend_grad():
        return np.asarray(score(_f(raw), mi.Bool(aligned(np.asarray(hit, bool)))), np.float64)


def golden_section(f, lo: float, hi: float, iterations: int = 30) -> float:
    """The minimiser of a unimodal ``f`` on ``[lo, hi]`` by golden-section search (``iterations`` steps)."""
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
    fa, fb = f(a), f(b)
    for _ in range(iterations):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - golden * (hi - lo)
            fa = f(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + golden * (hi - lo)
            fb = f(b)
    return 0.5 * (lo + hi)


def _rays(trace: PlanarTrace) -> RayBatch:
    n = trace.n
    return RayBatch(
        origin=mi.Point3f(0.0),
        direction=mi.Vector3f(1.0, 0.0, 0.0),
        beam=mi.UInt32(aligned(trace.beam.astype(np.uint32))),
        time=dr.zeros(mi.Float, n),
        ray_id=dr.arange(mi.UInt32, n),
    )


def nominal_beams(trace: PlanarTrace) -> EngineBeams:
    """Each beam meets one opaque element at its nominal range, or nothing (see the module docstring)."""
    met = np.isfinite(trace.nominal)
    start = np.concatenate([[0], np.cumsum(met)])
    n_elements = int(met.sum())
    table = ElementTable.from_elements(np.ones(max(n_elements, 1)), label=np.ones(max(n_elements, 1)))
    cos_incidence = _cos(trace.incidence[met])
    rounds = rounds_from_segments(start, np.arange(n_elements), trace.nominal[met], cos_incidence)
    hit = trace.hit
    return EngineBeams(
        table=table,
        rays=_rays(trace),
        rounds=rounds,
        z=_f(np.nan_to_num(trace.z)),
        hit=mi.Bool(aligned(hit)),
        hits=np.ones(n_elements),
        passes=np.zeros(n_elements),
        occupied=np.ones(n_elements, np.int64),
        ranges=trace.nominal[met],
        cos_incidence=cos_incidence,
        follows=scan_follows(trace.scan, trace.beam),
    )


def segment_beams(trace: PlanarTrace, classes: int = EVIDENCE_CLASSES, lines: bool = False) -> EngineBeams:
    """Each beam meets every cell with leave-out hits along it; elements carry counts and :func:`segment_labels`
    (telling line-like cells apart with ``lines``).

    The interception and the density's state read the incidence on each cell's surface (``seg_incidence``).
    """
    n_elements = trace.seg_range.size
    labels = trace_labels(trace, classes, lines).astype(np.uint32)
    table = ElementTable.from_elements(np.ones(max(n_elements, 1)), label=labels if n_elements else None)
    cos_incidence = _cos(trace.seg_incidence)
    rounds = rounds_from_segments(trace.seg_start, np.arange(n_elements), trace.seg_at, cos_incidence)
    return EngineBeams(
        table=table,
        rays=_rays(trace),
        rounds=rounds,
        z=_f(np.nan_to_num(trace.z)),
        hit=mi.Bool(aligned(trace.hit)),
        hits=trace.seg_hits.astype(np.float64),
        passes=trace.seg_passes.astype(np.float64),
        occupied=trace.seg_occupied.astype(np.int64),
        ranges=trace.seg_at.astype(np.float64),
        cos_incidence=cos_incidence,
        follows=scan_follows(trace.scan, trace.beam),
    )


RANGE_REFERENCE = 5.0  # m: the range at which an element intercepts by its counts alone (see permeability)
RANGE_LEAST = 0.2  # m: nearer elements intercept as if met at this range
COS_REFERENCE = 0.5  # |cos| of the incidence (60 deg) at which, or when unknown, an element intercepts by its counts
COS_LEAST = 0.05  # elements met more grazingly intercept as if met at this |cos| (87 deg)


def permeability(hits, passes, a, b, ranges=None, gamma=None, kappa=None, cos_incidence=None, eta=None):
    """The probability that an element intercepts the beam, from its leave-out counts (numpy or Dr.Jit; every
    argument per element).

    The counting estimate with a Beta(a, b) prior, ``p = (hits + a) / (hits + passes + a + b)``, raised to the
    power ``kappa`` (None: 1), is the interception of a beam that meets the element at :data:`RANGE_REFERENCE`.
    ``kappa > 1`` sharpens the contrast between cells: a cell whose hits are a small share of its visits (a
    person who stood there once, among many passes) intercepts much less than that share, a cell hit at most
    visits (a chair leg) nearly as often. Hits come in runs of scans (the person stood for a while), so a low
    share is mostly one event of the past. Fitted per occupancy class with the priors
    (:func:`fit_permeability`), the stray-hit cells took 0.95-2.7 on ten CARMEN logs (FHW 2.3: test NLL 3.918
    -> 3.901 nats per beam, one-draw histogram match 0.107 -> 0.078 m; docs/loop_results.md). With ``ranges`` (m) and
    ``gamma``, a beam that meets it at range ``r`` passes with probability ``(1 - p) ** ((r /
    RANGE_REFERENCE) ** gamma)``, as if it crossed ``(r / RANGE_REFERENCE) ** gamma`` such elements: a beam
    widens with range, and a cell that holds part of a thin thing (a chair leg, a person, a wall's end) stops
    more of a wide far beam than of a narrow near one (``gamma > 0``; 0: the counting estimate at every
    range). Fitted per occupancy class by likelihood (:func:`fit_permeability`), the stray-hit cells took
    0.14-0.61 on ten CARMEN logs (docs/loop_results.md); on synthetic traces it is found within 0.03 of the
    truth (tests/planar/test_range_interception.py). With ``cos_incidence`` (|cos| of the incidence at which the beam
    meets the element; NaN: unknown, as at :data:`COS_REFERENCE`) and ``eta``, the crossings are multiplied by
    ``(cos_incidence / COS_REFERENCE) ** eta``: a cell's counts do not know from which direction they came, and
    a wall's cells are passed by beams that graze along the wall and hit by beams that meet it head-on. Fitted
    for the occupied cells only (the incidence of a stray cell is its neighbouring wall's, not its own), it took
    0.93-2.05 on ten CARMEN logs, and the test NLL fell on all ten (Intel 3.176 -> 3.164, Orebro 3.836 -> 3.820;
    docs/loop_results.md).
    """
    p = (hits + a) / (hits + passes + a + b)
    xp = np if isinstance(p, np.ndarray) else dr  # the same formula on numpy and Dr.Jit arrays
    if kappa is not None:
        p = xp.exp(kappa * xp.log(p))
    if gamma is None:
        return p
    crossed = xp.exp(gamma * xp.log(xp.maximum(ranges, RANGE_LEAST) / RANGE_REFERENCE))
    if eta is not None:
        where = np.where if xp is np else dr.select
        cos = where(xp.isfinite(cos_incidence), xp.maximum(xp.minimum(cos_incidence, 1.0), COS_LEAST), COS_REFERENCE)
        crossed = crossed * xp.exp(eta * xp.log(cos / COS_REFERENCE))
    return 1.0 - xp.exp(xp.log(1.0 - p) * crossed)


def fit_permeability(
    beams: EngineBeams,
    model,
    steps: int = 120,
    tolerance: float | None = PERMEABILITY_TOLERANCE,
    start: tuple[np.ndarray, ...] | None = None,
) -> tuple[np.ndarray, ...]:
    """The Beta priors ``(a, b)`` of the cells' interception probabilities, their range exponents ``gamma``, their
    counts' exponents ``kappa`` and their incidence exponents ``eta`` (:func:`permeability`), one of each per
    occupancy class, by the one fitter (``eta`` of the occupied cells only, the others 0: :data:`WALLS`).

    Stray-hit cells (hits in fewer than a quarter of visits: people, clutter, grazing wall edges) and
    ``occ3`` occupied cells get their own prior: the same counts mean a different interception
    probability in the two classes. Backstops (:meth:`~mi_lidar.planar.trace.PlanarTrace.with_backstops`)
    have no counts: theirs is ``a / (a + b)`` of their own prior (their ``kappa`` stays 1: it would set the same
    number again).

    Only the interception probabilities move, so each segment's return density at the measured range
    is computed once (:func:`~mi_lidar.core.trace.cache_distributions`) and a step is a few gathers.
    The fit stops after at most ``steps`` steps, or once the mean score improved by less than
    ``tolerance`` (nats per beam; None: never) over 15 steps (on the Intel log after 50-64 of 120
    steps, within 1e-4 nats per beam of the 120-step loss). ``start``: the ``(a, b, gamma, kappa, eta)`` to start
    from (default 0.5, 0.5, 0, 1 and 0 each), e.g. the previous EM round's. ``kappa`` is kept within 0.2-5: the stray
    cells of beams in the open took 5 on ACES and FHW, and 14-20 with a bound of 20, the test NLL within 0.0002.
    """
    cache = RayCache.from_rounds(cache_distributions(beams.rounds, beams.table, model, beams.rays, beams.z))
    batch = cache.batch(np.arange(beams.n))
    hits, passes = _f(beams.hits), _f(beams.passes)
    occupied = mi.UInt32(aligned(beams.occupied.astype(np.uint32)))
    half, flat, one = np.full(OCCUPANCY_CLASSES, 0.5), np.zeros(OCCUPANCY_CLASSES), np.ones(OCCUPANCY_CLASSES)
    a0, b0, g0, k0, e0 = start if start is not None else (half, half, flat, one, flat)
    uncounted, walls = (np.isin(np.arange(np.size(k0)), c) for c in (UNCOUNTED, WALLS))
    k0, e0 = np.where(uncounted, 1.0, k0), np.where(walls, e0, 0.0)
    variables = [
        FitVariable("a", a0, lower=1e-3, upper=100.0, scale=0.5, transform="log"),
        FitVariable("b", b0, lower=1e-3, upper=100.0, scale=0.5, transform="log"),
        FitVariable("gamma", g0, lower=-3.0, upper=3.0, scale=0.3),
        FitVariable("kappa", k0, lower=0.2, upper=5.0, scale=0.3, transform="log"),
        FitVariable("eta", e0, lower=-3.0, upper=3.0, scale=0.3),
    ]
    ranges, cos_incidence = _f(beams.ranges), _f(beams.cos_incidence)
    counted, walls = _f(~uncounted), _f(walls)

    def objective(values, step: int) -> float:
        v = values()
        v["kappa"] = counted * v["kappa"] + (1.0 - counted)
        v["eta"] = walls * v["eta"]
        a, b, gamma, kappa, eta = (lookup(v[name], occupied) for name in INTERCEPTION_PARAMETERS)  # reproducible
        p = permeability(hits, passes, a, b, ranges, gamma, kappa, cos_incidence, eta)
        table = beams.table.replaced(p_hit=p)
        raw = mixture_log_likelihood(table, model, beams.rays, batch, beams.z, beams.hit)
        loss = -dr.mean(score(raw, beams.hit))
        dr.backward(loss)
        return float(loss[0])

    result = adam_fit(variables, objective, steps, lr=0.3, tolerance=tolerance)
    return tuple(np.asarray(result.values[name], np.float64) for name in INTERCEPTION_PARAMETERS)
