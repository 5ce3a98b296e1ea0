"""The models the planar benchmark compares, each fitted on training beams only and scored by the one engine.

=========  ===================================================================================
name       model (``docs/benchmark_planar.md``)
=========  ===================================================================================
M0         ideal ray cast + one Gaussian (Gazebo-style): sigma by 1-D search, P(miss) 1e-3 at a
           nominal hit; a nominal-miss beam returns (uniformly on [0, z_max]) with the training
           frequency (the protocol scores such returns 1e-3, an improper density; this keeps M0 proper)
M1         Probabilistic Robotics beam mixture, 6 global parameters (the one Adam fitter)
M2a, M2b   the same per nominal-range bin / per range x incidence bin; bins with < 300 training
           beams fall back to the range bin, then to M1
M3a, M3b   residual histograms per bin with the protocol's smoothing (the binned NP baseline)
P-Reg      thesis 3.3: P_null, mean, sigma by local linear kernel regression on range and incidence
NP-Reg     thesis 3.4: per-state histograms smoothed across states by a kernel (frequency polygon)
mi-lidar   the permeable map: every cell with leave-out hits is an element at its surface
           that intercepts the beam with its counting estimate (a Beta prior per occupancy class,
           fitted) raised to a power (per class, fitted: a cell hit in few of its many visits stops
           less than its share says), changed with the range and, for occupied cells, the incidence at
           which the beam meets it (an exponent each, fitted: :func:`~mi_lidar.planar.beams.permeability`),
           returns by an NP-Reg density conditioned on
           the cell's occupancy, evidence (how many leave-out hits; whether to tell them apart is
           chosen held out), range and incidence (on the cell's surface or by the protocol's line rule,
           chosen held out)
           (refined by EM over the segments, each return and each miss shared among the elements by
           their posterior, and counted by the posterior of the beam's own trace once its angular spread
           is known; its far tails scaled by likelihood); a beam that passes every cell listed for it
           meets a backstop behind the last (its own interception probability and return law: what
           is credited to it, shrunk to an unseen wall's,
           :meth:`~mi_lidar.planar.trace.PlanarTrace.with_backstops`), and one that passes it
           too escapes (the law of the returns and misses credited to escaping); a beam in the open (stray
           cells only) meets stray cells and a backstop of classes of its own; a beam's return
           comes from its own trace or, by fitted shares, from a neighbouring beam's or the nearer of
           the two (its angular spread, :mod:`~mi_lidar.planar.angular`); sampled scans share errors
           between neighbouring beams as the real training scans do (a Gaussian copula on the
           sampler's streams, :mod:`~mi_lidar.planar.correlation`; no effect on the NLL)
=========  ===================================================================================

Bandwidths, priors and mi-lidar's evidence classes and state incidence are chosen on the training scans only:
the learned models hold out every other training scan for the choice and are refitted on all training scans
with the chosen setting; the Beta priors, the tables' far tails and the angular spread are fitted by maximum
likelihood on the training beams, the shared errors on at most 45,000 training beams (250 scans of 180 beams).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_lidar.core.densities import BeamDensity, NPRegDensity, PhysicsDensity
from mi_lidar.core.densities.histogram import (
    _finish,
    count_states,
    fit_binned_histogram,
    fit_np_reg,
    kernel_smooth,
    support_end,
)
from mi_lidar.core.densities.preg import fit_p_reg
from mi_lidar.core.densities.samples import StateSamples, protocol_residual_edges
from mi_lidar.core.densities.tables import PSEUDO_SAMPLES, StateGrid
from mi_lidar.core.likelihood import element_shares
from mi_lidar.core.problem import fit_parts
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.streams import BeamCorrelation
from mi_lidar.planar.angular import AngularMixture, angular_mixture, fit_angular_shares, own_part_posterior
from mi_lidar.planar.beams import (
    EVIDENCE_CLASSES,
    LABELS_BEYOND,
    EngineBeams,
    base_model,
    fit_permeability,
    golden_section,
    nominal_beams,
    segment_beams,
    segment_labels,
)
from mi_lidar.planar.correlation import fit_beam_correlation
from mi_lidar.planar.tails import FAR, fit_tails, match_misses, match_short_returns
from mi_lidar.planar.trace import BACKSTOP, OPEN_BACKSTOP, PlanarTrace

RANGE_EDGES = [float(e) for e in np.linspace(0.0, 40.0, 18)] + [1.0e9]  # 17 bins over 0-40 m (M2a, M3a)
INCIDENCE_EDGES = [0.0, 20.0, 40.0, 55.0, 65.0, 75.0, 82.0, 90.0]  # plus the unknown bin (M2b, M3b)
MIN_BEAMS = 300


def samples_of(trace: PlanarTrace) -> StateSamples:
    """The nominal state of every beam and its measurement."""
    return StateSamples(
        nominal=trace.nominal,
        incidence=trace.incidence,
        beam=trace.beam,
        label=np.zeros(trace.n, np.int64),
        z=trace.z,
        hit=trace.hit,
    )


def initial_credit(trace: PlanarTrace) -> np.ndarray:
    """(B,) the segment each beam's outcome is first credited to (-1: the escape state): its first ``occ3``
    occupied segment, or its backstop (:meth:`~mi_lidar.planar.trace.PlanarTrace.with_backstops`, which
    ``trace`` holds) for a return more than :data:`~mi_lidar.planar.tails.FAR` behind it; a beam in the open
    (stray cells only), its backstop whatever it reported (credited to the escape state, its misses left that
    backstop no P(null) from which the EM could give them back)."""
    first = trace.first_occupied()
    counts = np.diff(trace.seg_start)
    last = np.maximum(trace.seg_start[1:] - 1, 0)
    kind = np.where(counts > 0, trace.seg_occupied[last], -1)
    far = (kind == BACKSTOP) & trace.hit & (trace.z > trace.seg_at[last] + FAR)
    return np.where(far | (kind == OPEN_BACKSTOP), last, first)


def fit_m0(train: EngineBeams, samples: StateSamples, z_max: float) -> SensorModel:
    """M0: sigma by golden-section search on the training NLL (the one score)."""
    escaped = ~samples.met
    escape = float(np.clip(samples.hit[escaped].mean() if escaped.any() else 0.0, 1e-3, 1.0 - 1e-3))

    def density(log_sigma: float) -> PhysicsDensity:
        return PhysicsDensity(sigma0=float(np.exp(log_sigma)), k=0.0, p_null=1e-3, escape_return=escape, z_max=z_max)

    def nll(log_sigma: float) -> float:
        return float(-np.mean(train.log_likelihood(base_model(density(log_sigma)))))

    return base_model(density(golden_section(nll, np.log(0.003), np.log(2.0))))


def fit_beam(
    train: EngineBeams,
    samples: StateSamples,
    grid: StateGrid,
    z_max: float,
    start: BeamDensity | None,
    fallback: Callable[[np.ndarray], np.ndarray] | None,
    steps: int = 150,
) -> SensorModel:
    """M1 / M2: the beam mixture on ``grid`` by the one fitter; thin states take ``fallback``'s parameters."""
    density = BeamDensity(grid=grid, z_max=z_max, escape="shared" if grid.size == 1 else "own")
    if start is not None:  # start every state from the coarser model
        for key in ("logits", "log_sigma", "log_lambda"):
            width = 4 if key == "logits" else 1
            parent = np.asarray(start.params[key]).reshape(-1, width)
            density.params[key] = type(density.params[key])(np.tile(parent[0], grid.size + 1).astype(np.float32))
    model = base_model(density)
    fit_parts(model, train.problem(), [density], steps=steps)
    if fallback is not None:
        met = samples.met
        state = np.full(samples.n, grid.size)
        state[met] = grid.index_np(samples.nominal[met], samples.incidence[met])
        thin = np.bincount(state, minlength=grid.size + 1) < MIN_BEAMS
        for key in ("logits", "log_sigma", "log_lambda"):
            width = 4 if key == "logits" else 1
            values = np.asarray(density.params[key]).reshape(-1, width).copy()
            values[thin] = fallback(key)[thin]
            density.params[key] = type(density.params[key])(values.ravel().astype(np.float32))
    return model


def fit_beam_family(train: EngineBeams, samples: StateSamples, z_max: float) -> dict[str, SensorModel]:
    """M1, M2a and M2b with the protocol's fall-backs."""
    m1 = fit_beam(train, samples, StateGrid(), z_max, None, None)
    one = m1.density

    def global_values(key: str) -> np.ndarray:
        width = 4 if key == "logits" else 1
        row = np.asarray(one.params[key]).reshape(-1, width)[0]
        return np.tile(row, (len(RANGE_EDGES) - 1 + 1, 1)) if key else row

    range_grid = StateGrid(range_edges=RANGE_EDGES)
    m2a = fit_beam(train, samples, range_grid, z_max, one, global_values)
    both_grid = StateGrid(range_edges=RANGE_EDGES, incidence_edges=INCIDENCE_EDGES)

    def range_values(key: str) -> np.ndarray:
        width = 4 if key == "logits" else 1
        per_range = np.asarray(m2a.density.params[key]).reshape(-1, width)  # (R + 1, width), escape last
        inner = np.tile(per_range[:-1], (both_grid.n_incidence, 1))  # StateGrid order: incidence-major
        return np.concatenate([inner, per_range[-1:]])

    m2b = fit_beam(train, samples, both_grid, z_max, one, range_values)
    return {"M1": m1, "M2a": m2a, "M2b": m2b}


def fit_histograms(samples: StateSamples, z_max: float) -> dict[str, SensorModel]:
    """M3a and M3b: the protocol's binned histograms."""
    edges = protocol_residual_edges(z_max)
    out = {}
    for name, grid in (
        ("M3a", StateGrid(range_edges=RANGE_EDGES)),
        ("M3b", StateGrid(range_edges=RANGE_EDGES, incidence_edges=INCIDENCE_EDGES)),
    ):
        out[name] = base_model(fit_binned_histogram(samples, grid, edges=edges, z_max=z_max))
    return out


def fine_grid(samples: StateSamples, labels: int = 1) -> StateGrid:
    """The fine state grid of the learned models: 0.5 m ranges to the farthest nominal range, 5 deg incidences."""
    far = float(np.nanmax(samples.nominal[samples.met])) if np.any(samples.met) else 10.0
    return StateGrid(
        range_edges=[float(e) for e in np.arange(0.0, far + 0.5, 0.5)] + [1.0e9],
        incidence_edges=[float(e) for e in np.arange(0.0, 90.0 + 1e-9, 5.0)],
        n_labels=labels,
    )


def fit_learned(train: PlanarTrace, z_max: float, family: str) -> tuple[SensorModel, tuple]:
    """P-Reg or NP-Reg: settings chosen on held-out training scans, then refitted on all training scans.

    Returns:
        The model and the chosen setting (bandwidths; P-Reg's escape law; NP-Reg's uniform share and support
        reach).
    """
    fit_part = train.take(train.scan % 2 == 0)
    check = nominal_beams(train.take(train.scan % 2 == 1))

    def held_out(density) -> float:
        return float(-np.mean(check.log_likelihood(base_model(density))))

    samples = samples_of(train)
    if family == "p_reg":
        _, table = fit_p_reg(samples_of(fit_part), held_out, z_max=z_max)
        h_r, h_d, escape, _ = min(table, key=lambda row: row[-1])
        density, _ = fit_p_reg(
            samples, lambda d: 0.0, h_ranges=(h_r,), h_incidences=(h_d,), escapes=(escape,), z_max=z_max
        )
        setting: tuple = (h_r, h_d, escape)
    else:
        grid = fine_grid(samples)
        _, table = fit_np_reg(samples_of(fit_part), grid, held_out, z_max=z_max)
        h_r, h_i, u, reach, h_null, _ = min(table, key=lambda row: row[-1])
        density, _ = fit_np_reg(
            samples,
            grid,
            lambda d: 0.0,
            h_ranges=(h_r,),
            h_incidences=(h_i,),
            uniforms=(u,),
            reaches=(reach,),
            h_nulls=(h_null,),
            z_max=z_max,
        )
        setting = (h_r, h_i, u, reach, h_null)
    return base_model(density), setting


def credited_segments(beams: EngineBeams, seg_start: np.ndarray, model: SensorModel) -> tuple[np.ndarray, ...]:
    """Each segment's share in what the sensor reported, a return or a miss, beam by beam: the E step of the
    permeable map's EM (the posterior of :func:`~mi_lidar.core.likelihood.element_shares`).

    ``beams``: segment beams with their interception probabilities (:func:`~mi_lidar.planar.beams.segment_beams`);
    ``seg_start``: (B + 1,) the first segment of every beam, as in the trace they were built from.
    Returns ``(beam, segment, share)``, (M,) each: ``segment`` indexes the segments (-1: the beam passed every
    segment, the escape state); a beam's shares sum to 1, and rows of no share are left out.
    """
    with dr.suspend_grad():
        shares = element_shares(beams.table, model, beams.rays, beams.rounds, beams.z, beams.hit)
    beam, found, _, share = shares.credited()  # a planar beam meets one segment per round
    return beam, np.where(found >= 0, seg_start[beam] + found, -1), share


def backstop_prior(counts: np.ndarray, grid: StateGrid, classes: int, pseudo: float = PSEUDO_SAMPLES) -> np.ndarray:
    """``counts`` (S + 1, B + 1) per state (escape last, no-returns in the last column) with every backstop state
    (label ``2 * classes``, :func:`~mi_lidar.planar.beams.segment_labels`) given ``pseudo`` more outcomes,
    distributed as those of the occupied cells of the least evidence (label ``classes``) at its range and
    incidence; in place.

    A backstop returns and misses by what the EM credits to it: outdoors ground or foliage far behind a bush,
    or nothing. Where little is credited to it, it returns as a wall the map has not seen: indoors, a beam
    that passed its last listed cell mostly meets one right behind it (FHW test NLL 3.959 with the backstop
    labelled as such a wall; 3.982 with a law of its own unshrunk; 3.941 shrunk).
    """
    block = grid.size // grid.n_labels
    unseen = counts[classes * block : (classes + 1) * block]
    total = unseen.sum(axis=-1, keepdims=True)
    share = np.divide(unseen, total, out=np.zeros_like(unseen), where=total > 0)
    counts[2 * classes * block : (2 * classes + 1) * block] += pseudo * share
    return counts


@dataclass
class PermeableMap:
    """mi-lidar's planar model: a return density per segment state, the Beta prior of the cells, the angular spread.

    Attributes:
        model: the sensor model (its density conditions on range, incidence, cell occupancy and evidence).
        a, b: (5,) the Beta priors of the elements' interception probabilities, one per occupancy class
            (stray-hit cells, occupied cells, backstops, and the backstops and stray cells of beams in the open:
            :data:`~mi_lidar.planar.trace.BACKSTOP`).
        gamma: (5,) how the interception of each class grows with the range at which a beam meets an element,
        kappa: (5,) the exponent of each class's counting estimate,
        eta: (5,) how the interception of each class grows as the beam meets an element more head-on
            (:func:`~mi_lidar.planar.beams.permeability`; fitted for the occupied cells only).
        classes: evidence classes of the segment labels (:func:`~mi_lidar.planar.beams.segment_labels`).
        states_on_lines: the density's states read the protocol's line incidence, not the surface's
            (:func:`~mi_lidar.planar.beams.segment_beams`).
        angular: the share of each neighbouring beam's trace alone in a beam's return, and
        footprint: the share of each footprint (the nearer of the beam's and a neighbour's returns)
            (:class:`~mi_lidar.planar.angular.AngularMixture`).
        correlation: how much neighbouring beams share their errors when sampled
            (:func:`~mi_lidar.planar.correlation.fit_beam_correlation`).
        shared_errors: that fit's summary: PIT lag correlations of the real training scans, of scans
            sampled with ``correlation`` and of scans sampled with independent beams.
    """

    model: SensorModel
    a: np.ndarray
    b: np.ndarray
    gamma: np.ndarray
    kappa: np.ndarray
    eta: np.ndarray
    classes: int = EVIDENCE_CLASSES
    states_on_lines: bool = False
    angular: float = 0.0
    footprint: float = 0.0
    correlation: BeamCorrelation = BeamCorrelation()
    shared_errors: dict = dataclasses.field(default_factory=dict)

    @property
    def interception(self) -> tuple[np.ndarray, ...]:
        """``(a, b, gamma, kappa, eta)``: what sets every element's interception probability
        (:func:`~mi_lidar.planar.beams.fit_permeability`)."""
        return self.a, self.b, self.gamma, self.kappa, self.eta

    def segments(self, trace: PlanarTrace) -> EngineBeams:
        """The engine's view of ``trace`` under this map (every segment, interception from its counts)."""
        beams = segment_beams(trace.with_backstops(), self.classes, self.states_on_lines)
        beams = beams.with_permeability(*self.interception)
        return dataclasses.replace(beams, correlation=self.correlation)

    def beams(self, trace: PlanarTrace) -> AngularMixture:
        """The beams of ``trace`` under this map, with their angular spread."""
        return angular_mixture(trace, self.segments, self.angular, self.footprint)


def fit_milidar(
    train: PlanarTrace,
    z_max: float,
    bandwidths: tuple[float, float, float, float, float],
    classes=(1, EVIDENCE_CLASSES),
) -> PermeableMap:
    """mi-lidar's permeable map (see the module docstring), its evidence classes and state incidence chosen held out.

    Each candidate number of evidence classes, with the density's states on the surface's incidence and on
    the protocol's line incidence, is fitted (all EM rounds: after one, Edmonton chose 1 class
    where 5 scored 0.018 nats per test beam better) on the even training scans and
    scored on the odd ones (without the tails' fit, which all candidates would share); the best is
    refitted on all training scans (:func:`fit_permeable_map`). The interception reads the surface's incidence
    either way. States on the surface's incidence, known on more cells, scored 0.015-0.019 nats per test beam
    better on Intel and FHW; on the line incidence 0.007-0.015 better on ACES, Orebro and Seattle, where
    clutter given an incidence blurred the walls' states (docs/loop_results.md). Last, how much neighbouring beams share
    their errors (:func:`fit_correlation`): it changes the samples only, not the held-out score, so the
    trials go without it.
    A log whose cells are seen by many scans gains from telling well-seen walls from cells seen once;
    a sparser log spreads its returns over too many states and keeps occupancy alone.
    """
    prior = None  # each fit of the Beta priors starts from the last one's
    candidates = [(k, on_lines) for k in classes for on_lines in (False, True)]
    fit_part, check = train.take(train.scan % 2 == 0), train.take(train.scan % 2 == 1)
    trials, scores = [], []
    for k, on_lines in candidates:
        start = trials[-1].interception if trials else None
        trials.append(
            fit_permeable_map(fit_part, z_max, bandwidths, k, tails=False, prior=start, states_on_lines=on_lines)
        )
        scores.append(-float(np.mean(trials[-1].beams(check).log_likelihood(trials[-1].model))))
    best = int(np.argmin(scores))
    (k, on_lines), prior = candidates[best], trials[best].interception
    del trials
    fitted = fit_permeable_map(train, z_max, bandwidths, k, prior=prior, states_on_lines=on_lines)
    fitted.correlation, fitted.shared_errors = fit_correlation(fitted, train)
    return fitted


def fit_permeable_map(
    train: PlanarTrace,
    z_max: float,
    bandwidths: tuple[float, float, float, float, float],
    classes: int = EVIDENCE_CLASSES,
    rounds: int = 3,
    steps: int = 120,
    tails: bool = True,
    prior: tuple[np.ndarray, ...] | None = None,
    states_on_lines: bool = False,
) -> PermeableMap:
    """mi-lidar's permeable map with ``classes`` evidence classes (see the module docstring), the density's states
    on the protocol's line incidence with ``states_on_lines`` (:func:`~mi_lidar.planar.beams.segment_beams`).

    Every beam's segments end in a backstop (:meth:`~mi_lidar.planar.trace.PlanarTrace.with_backstops`:
    a class with its own Beta prior and its own label, :func:`backstop_prior`; a beam in the open, with stray
    cells only, has a backstop and stray cells of classes of their own).
    Start: NP-Reg tables from each beam's first occupied cell (its surface, incidence and label), or its
    backstop for a return more than :data:`~mi_lidar.planar.tails.FAR` behind it or for a beam in the open
    (:func:`initial_credit`),
    and the kernel ``bandwidths`` ``(h_range, h_incidence, uniform, reach, h_null)`` chosen for NP-Reg on held-out
    training scans (:func:`~mi_lidar.core.densities.histogram.kernel_smooth`); then ``rounds`` times: fit the
    Beta priors (a, b), the range, counts' and incidence exponents (gamma, kappa, eta) of the interception probabilities
    (:func:`~mi_lidar.planar.beams.permeability`) by the one fitter, then
    :data:`CREDIT_STEPS` times share each return and each miss among the elements that could have produced it
    (segments, the backstop, the escape state) by their posterior (:func:`credited_segments`, the E step) and
    re-estimate the tables from those shares (the M step); then the Beta priors again.
    Shares, not a hard credit to the most likely element: when a passed thin cell and the wall behind it
    explain a return alike, the hard credit gave every such return to the cell and every miss to what lies
    behind it, so the backstop's law missed nearly always and walls that share the cell's state took over
    the misses (tests/planar/test_backstops.py; Intel test NLL 3.225 -> 3.191, one-draw hist L1 0.037-0.053 ->
    0.021-0.026 m; Freiburg campus 3.997 -> 3.967). The E step costs about a tenth of a Beta fit, so each fit
    is followed by several (one per fit: Intel 3.197; the EM is slow where two elements explain the same outcomes).
    Crediting every miss to the beam's first occupied cell, as before, counted a miss of a beam that had
    passed its cells twice, in that cell's P(no return) and in the escape state's (Freiburg campus: escape
    P(no return) 0.87, 30 % of its training beams predicted to miss where 26 % did, sampled hit rate 0.699
    against 0.741 measured; now 0.72 and 0.735);
    then the angular spread's shares (below) and :data:`SPREAD_CREDIT_STEPS` more E and M steps in which each
    outcome counts by the posterior that the beam's own trace, not a neighbour's, produced it
    (:func:`~mi_lidar.planar.angular.own_part_posterior`): the tables had learned the neighbours' returns as the
    beam's own, and the spread drew them again (Acapulco's beams that met no cell: 23.5 % of them returned in
    sampled training scans at a median 25.3 m where 21.4 % did at 36.6 m; now 18.2 % at 40.7 m; test NLL
    4.012 -> 4.007 and the histogram match 0.121 -> 0.075 m; the same steps counting every outcome in full
    changed nothing, 4.012; on ten CARMEN logs the test NLL fell 0-0.008 and the histogram match moved either
    way, docs/loop_results.md);
    then the tables' far tails
    (:func:`~mi_lidar.planar.tails.fit_tails`, then
    :func:`~mi_lidar.planar.tails.match_short_returns`, on evenly spaced training scans of at most
    :data:`TAIL_BEAMS` beams) and their no-return probabilities
    (:func:`~mi_lidar.planar.tails.match_misses`, per range band of the first occupied cell, on all
    training beams: no-returns come in runs of whole scans); none with ``tails=False``; last, the
    angular spread (the shares of the neighbours alone and of the footprints) by maximum likelihood on the
    training beams. Its beams are sampled independently until :func:`fit_correlation` sets how much
    neighbours share their errors.
    Every fit of the Beta priors and exponents starts from the previous one's, the first from ``prior`` (default
    0.5, 0.5, 0, 1 and 0 each): a starting point, not a constraint.
    """
    h_r, h_i, u, reach, h_null = bandwidths
    end = support_end(samples_of(train), reach, z_max)
    grid = fine_grid(samples_of(train), labels=2 * classes + LABELS_BEYOND)
    edges = protocol_residual_edges(z_max)
    traced = train.with_backstops()
    labels = segment_labels(traced.seg_occupied, traced.seg_hits, classes)
    state_incidence = traced.seg_line_incidence if states_on_lines else traced.seg_incidence

    def tables(beam: np.ndarray, chosen: np.ndarray, share: np.ndarray) -> NPRegDensity:
        """Tables from the returns and misses of training beams ``beam``, each counted in segment ``chosen``
        (-1: the escape state) with weight ``share``."""
        seg = np.maximum(chosen, 0)
        assigned = StateSamples(
            nominal=np.where(chosen >= 0, traced.seg_at[seg], np.nan),
            incidence=np.where(chosen >= 0, state_incidence[seg], np.nan),
            beam=train.beam[beam],
            label=np.where(chosen >= 0, labels[seg], 0),
            z=train.z[beam],
            hit=train.hit[beam],
            weight=share,
        )
        counts = backstop_prior(count_states(assigned, grid, edges), grid, classes)
        smoothed = kernel_smooth(grid, counts[:-1], h_r, h_i, h_null)
        mass, p_null = _finish(np.concatenate([smoothed, counts[-1:]]), e_kernel=True)
        return NPRegDensity(grid=grid, edges=edges, mass=mass, p_null=p_null, shape="polygon", uniform=u, z_max=end)

    density = tables(np.arange(train.n), initial_credit(traced), np.ones(train.n))
    beams = segment_beams(traced, classes, states_on_lines)
    for _ in range(rounds):
        prior = fit_permeability(beams, base_model(density), steps, start=prior)
        permeable = beams.with_permeability(*prior)
        for _ in range(CREDIT_STEPS):
            density = tables(*credited_segments(permeable, traced.seg_start, base_model(density)))
        del permeable
    a, b, gamma, kappa, eta = fit_permeability(beams, base_model(density), steps, start=prior)
    del beams  # the mixture below holds these segments again, seven times: one set at a time
    fitted = PermeableMap(
        model=base_model(density),
        a=a,
        b=b,
        gamma=gamma,
        kappa=kappa,
        eta=eta,
        classes=classes,
        states_on_lines=states_on_lines,
    )
    mixture = fitted.beams(train)

    def angular_shares() -> np.ndarray:
        """Fit the spread's shares (the map's and the mixture's); returns the (5, B) raw part log-likelihoods
        they were fitted on."""
        raw = mixture.raw_parts(fitted.model)
        fitted.angular, fitted.footprint = fit_angular_shares(raw, mixture.hit)
        mixture.weight, mixture.footprint = fitted.angular, fitted.footprint
        return raw

    raw = angular_shares()
    for _ in range(SPREAD_CREDIT_STEPS):
        own = own_part_posterior(raw, mixture.shares())
        beam, chosen, share = credited_segments(mixture.parts[0], traced.seg_start, fitted.model)
        density = tables(beam, chosen, share * own[beam])
        fitted.model = base_model(density)
        raw = angular_shares()
    if tails:
        part = train.take(np.isin(train.scan, evenly_spaced_scans(train.scan, TAIL_BEAMS)))
        some = fitted.beams(part)
        density = match_short_returns(some, part, fit_tails(some, density))
        first_range = train.first_occupied_range()
        fitted.model = base_model(match_misses(mixture, density, first_range, RANGE_EDGES))
        angular_shares()
    return fitted


SPREAD_CREDIT_STEPS = 2  # E and M steps of the tables with the angular spread (see fit_permeable_map)
CREDIT_STEPS = 4  # E and M steps of the tables per fit of the Beta priors (see fit_permeable_map)
CORRELATION_BEAMS = 45_000  # at most this many training beams (whole scans) measure the shared errors
TAIL_BEAMS = 30_000  # at most this many training beams (whole scans) fit the tables' tails


def evenly_spaced_scans(scan: np.ndarray, beams: int = CORRELATION_BEAMS) -> np.ndarray:
    """Evenly spaced scans (of the scan index of every beam, ``scan``) with at most ``beams`` beams in all."""
    scans = np.unique(scan)
    most = max(1, beams * scans.size // max(scan.size, 1))  # scans of that many beams
    return scans[:: max(1, -(-scans.size // most))]


def fit_correlation(fitted: PermeableMap, train: PlanarTrace) -> tuple[BeamCorrelation, dict]:
    """How much neighbouring beams share their errors (:func:`~mi_lidar.planar.correlation.fit_beam_correlation`),
    measured on evenly spaced training scans of at most :data:`CORRELATION_BEAMS` beams in all (the cost
    follows the beams, whatever the scanner's resolution)."""
    part = train.take(np.isin(train.scan, evenly_spaced_scans(train.scan)))
    mixture = dataclasses.replace(fitted, correlation=BeamCorrelation()).beams(part)

    def sample(correlation: BeamCorrelation, seed: int):
        return mixture.with_correlation(correlation).sample(fitted.model, seed)

    correlation, summary = fit_beam_correlation(sample, part.z, part.hit, part.scan, part.beam)
    lags = {k: np.round(np.asarray(v, np.float64), 4).tolist() for k, v in summary.items() if k != "lags"}
    return correlation, {"lags": [int(k) for k in summary["lags"]], **lags}
