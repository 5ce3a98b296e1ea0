"""The one likelihood: the pass-through mixture of return densities along each ray, and its one floor.

Along a ray the elements ``k = 1..K`` are met in order (virtual elements of effects first, then the
traced ones, then the density's *escape* law for a beam that met nothing more). With
``pi_k = prod_{j<k} (1 - p_j)`` the probability of reaching element ``k``, it returns the beam with
probability ``pi_k p_k (1 - drop_k)`` at a range drawn from its return density ``f_k``, loses it
with ``pi_k p_k drop_k``, and lets it pass otherwise. So

* a measured return at ``z`` has density ``sum_k pi_k p_k (1 - drop_k) f_k(z)`` (1/m);
* a miss has probability ``sum_k pi_k p_k drop_k + pi_{K+1}``.

The sensor reports only ranges within its window ``[min_range, max_range]``: a return drawn outside
is lost like a dropped beam, so ``drop_k`` includes the share of ``f_k`` outside the window
(:meth:`~mi_lidar.core.sensor_model.SensorModel.censor`; the sampler drops such draws alike).

When the log's intensities are scored too, a return at ``z`` with intensity ``I`` has the joint
density ``sum_k pi_k p_k (1 - drop_k) f_k(z) g_k(I)``, with ``g_k`` the density per sensor unit of the
model's :class:`~mi_lidar.core.intensity.IntensityModel` for element ``k``: the element that explains
the range must explain the intensity as well.

:func:`mixture_log_likelihood` evaluates this with gradients on compact trace records
(:mod:`mi_lidar.core.trace`): each round works only on the rays that met an element in it and reads
the running sums of its rays from the previous round (``prev``); a ray's sums are written when its
last element has been folded in. Beams fanned out into sub-rays by a footprint effect are scored
from the sub-rays' return moments by that effect (:meth:`FootprintEffect.combine_log_likelihood`),
which loses the combined law's mass outside the window to the miss.

**One scoring rule, one floor** (:func:`score`): a return counts as the probability of its
``RESOLUTION`` = 1 cm range bin (density x 0.01 m, the sensor's resolution and the thesis's
discretised evaluation), a miss as its probability, and every ray's probability is floored softly
at ``FLOOR`` = 1e-9: ``log(p + FLOOR)``. A return no element can explain then costs 20.7 nats
instead of making a mean infinite, and still has a gradient. Every NLL mi-lidar prints (compare,
diagnose, calibrate, the planar benchmark) and every fit uses this score, so they are comparable.
With intensities, a return counts as the probability of its 1 cm x 1 unit (range, intensity) bin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.effects.base import SubRayMoments
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment, log_density, range_moments
from mi_lidar.core.trace import CachedBatch, Round, Rounds

RESOLUTION = 0.01  # m: a return scores the probability of its 1 cm range bin
FLOOR = 1e-9  # probability floor of every scored ray
LOG_RESOLUTION = math.log(RESOLUTION)
LOG_FLOOR = math.log(FLOOR)
TINY = 1e-12  # probabilities are clamped here before logs


def logaddexp(a: mi.Float, b: mi.Float) -> mi.Float:
    """``log(exp(a) + exp(b))`` per lane, exact where either is -inf."""
    high = dr.maximum(a, b)
    safe = dr.select(dr.isinf(high), 0.0, high)
    return dr.select(dr.isinf(high), high, safe + dr.log(dr.exp(a - safe) + dr.exp(b - safe)))


def score(ll: mi.Float, hit: mi.Bool) -> mi.Float:
    """Scored log-likelihood (nats) from the raw mixture ``ll`` (log density for returns, log P for misses).

    Returns ``log(P + FLOOR)`` with ``P = density * RESOLUTION`` for returns and ``P(miss)`` for
    misses (see the module docstring).
    """
    return logaddexp(dr.select(hit, ll + LOG_RESOLUTION, ll), dr.opaque(mi.Float, LOG_FLOOR))


@dataclass
class Sums:
    """Running sums of the mixture along each ray (nats).

    Attributes:
        log_mix: ``log sum_k pi_k p_k (1 - drop_k) f_k(z)`` over the elements so far (-inf: none).
        log_pass: ``log pi``: the probability of reaching the next element.
        log_lost: ``log sum_k pi_k p_k drop_k``: the beams lost so far (-inf: none).
    """

    log_mix: mi.Float
    log_pass: mi.Float
    log_lost: mi.Float

    @classmethod
    def start(cls, n: int) -> Sums:
        return cls(dr.full(mi.Float, -dr.inf, n), dr.zeros(mi.Float, n), dr.full(mi.Float, -dr.inf, n))

    def terms(self, p: mi.Float, drop: mi.Float, log_f: mi.Float) -> tuple[mi.Float, mi.Float]:
        """The next element's share: ``log pi p (1 - drop) f(z)`` (it returns the measured range) and
        ``log pi p drop`` (it loses the beam)."""
        drop = dr.zeros(mi.Float, dr.width(p)) + drop
        log_p = dr.log(dr.clip(p, TINY, 1.0))
        term = self.log_pass + log_p + dr.log(dr.clip(1.0 - drop, TINY, 1.0)) + log_f
        lost = self.log_pass + log_p + dr.log(dr.clip(drop, TINY, 1.0))
        return term, lost

    def fold(self, valid: mi.Bool, p: mi.Float, drop: mi.Float, log_f: mi.Float) -> Sums:
        """Add the next element (probabilities ``p``, ``drop``; log density ``log_f`` of the measured range)."""
        drop = dr.zeros(mi.Float, dr.width(p)) + drop
        term, lost = self.terms(p, drop, log_f)
        return Sums(
            log_mix=dr.select(valid, logaddexp(self.log_mix, term), self.log_mix),
            log_pass=self.log_pass + dr.select(valid, dr.log(dr.clip(1.0 - p, TINY, 1.0)), 0.0),
            log_lost=dr.select(valid & (drop > 0), logaddexp(self.log_lost, lost), self.log_lost),
        )

    def gather(self, index: mi.UInt32) -> Sums:
        """The sums at ``index`` (distinct indices: see :func:`_previous`)."""
        return Sums(*(_previous(v, index) for v in (self.log_mix, self.log_pass, self.log_lost)))

    def value(self, hit: mi.Bool) -> mi.Float:
        """Raw log-likelihood: log density of the return where ``hit``, else log P(miss)."""
        return dr.select(hit, self.log_mix, logaddexp(self.log_lost, self.log_pass))


def _previous(running: mi.Float, prev: mi.UInt32) -> mi.Float:
    """The previous round's running sums read at ``prev``, with gradients.

    The indices of a round are distinct, so the gather's derivative (a scatter-add into an array as
    long as the previous round) is compiled without conflict handling. Dr.Jit's default mode on the
    LLVM backend would expand the target per thread and write its length into the kernel as a
    constant; that length changes with every batch of rays, so the backward kernel of every round
    would be compiled anew at every step of a geometry fit.
    """
    return dr.gather(mi.Float, running, prev, mode=dr.ReduceMode.NoConflicts)


def _add_at(target: mi.Float, value: mi.Float, index: mi.UInt32, active: mi.Bool) -> mi.Float:
    """``target`` plus ``value`` scattered (added) to lanes ``index`` where ``active`` (keeps gradients)."""
    out = mi.Float(target)
    dr.scatter_reduce(dr.ReduceOp.Add, out, value, index, active)
    return out


def round_segment(table, model, rays: RayBatch, r: Round) -> tuple[Segment, RayBatch]:
    """The segments of round ``r`` before the density and effects, and the rays of its entries.

    Args:
        table: the :class:`~mi_lidar.core.elements.ElementTable` (may carry gradients).
        model: the sensor model.
        rays: the batch after :meth:`SensorModel.prepare_rays` (and fan-out).
        r: the round.
    """
    sub = rays.take(r.ray)
    valid = dr.full(mi.Bool, True, r.width)
    if r.cached is None:
        return table.segment(r, valid, r.element, sub.origin, sub.direction, model.range_sigma), sub
    return table.cached_segment(r, valid, model.range_sigma), sub


def _entry_log_density(model, table, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
    """Log density (1/m) of ``z`` under each lane's return law (the smoothed surrogate while fitting ellipsoids)."""
    if table.smoothing > 0:
        from mi_lidar.core.smoothing import smoothed_log_density

        return smoothed_log_density(seg, z, table.smoothing)
    return model.density.log_prob(seg, z, rays)


def mixture_log_likelihood(
    table, model, rays: RayBatch, rounds, measured: mi.Float, hit: mi.Bool, intensity: mi.Float | None = None
) -> mi.Float:
    """Per-ray raw log-likelihood (nats) of measured returns under the pass-through mixture.

    Args:
        table: the element table (its arrays may carry gradients).
        model: the sensor model (its density, effects and their parameters may carry gradients).
        rays: the batch the rounds were traced for (world frame, before ray perturbations).
        rounds: its trace: compact :class:`Rounds` (from :func:`~mi_lidar.core.trace.trace_rounds`)
            or a :class:`CachedBatch` of cached rays.
        measured: (B,) measured ranges, m (ignored where ``hit`` is False).
        hit: (B,) True where the sensor reported a return.
        intensity: optional (B,) measured intensities (sensor units; NaN where unknown), scored
            jointly with the range by the model's intensity model. Not supported with footprint
            effects or cached batches.

    Returns:
        (B,) log density (1/m, times 1/unit with intensities) of the measured return and log P(miss)
        for misses; use
        :func:`score` for the floored, discretised value every report prints.
    """
    rays = model.prepare_rays(rays)
    fan = model.fan_out(rays)
    if intensity is not None and (fan is not None or isinstance(rounds, CachedBatch)):
        raise ParameterError(
            "intensities are scored on traced rounds of single beams only: drop the footprint effect "
            "(mixed_pixels, multiple_returns) or score ranges alone"
        )
    if fan is not None:
        return _footprint_log_likelihood(table, model, fan, rounds, measured, hit)
    z = dr.select(hit, measured, 0.0)
    sums = _fold_virtual(model, rays, z)
    if isinstance(rounds, CachedBatch):
        sums = _fold_cached(table, model, rays, rounds, z, sums)
    else:
        sums = _fold_rounds(table, model, rays, rounds, z, sums, intensity)
    escape = _escape_law(model, rays, z)
    if escape is not None:
        sums = sums.fold(*escape)
    return sums.value(hit)


def _fold_virtual(model, rays: RayBatch, z: mi.Float) -> Sums:
    """The sums after the effects' virtual elements (outliers, clutter: their own Gaussian law, inside the window)."""
    sums = Sums.start(rays.width)
    for seg in model.virtual_segments(rays):
        seg = model.segment_law(seg, rays, virtual=True)
        sums = sums.fold(seg.valid, seg.p, seg.drop, log_density(seg, z))
    return sums


def _escape_law(model, rays: RayBatch, z: mi.Float) -> tuple | None:
    """``(valid, p, drop, log_f)`` of the density's escape segment at range ``z``, or None when it has none."""
    escape = model.density.escape(rays)
    if escape is None:
        return None
    escape = model.segment_law(escape, rays, escape=True)
    return (escape.valid, escape.p, *model.censor(escape, model.density.log_prob(escape, z, rays), rays))


def _fold_rounds(
    table,
    model,
    rays: RayBatch,
    rounds: Rounds,
    z: mi.Float,
    sums: Sums,
    intensity: mi.Float | None = None,
    shares: list | None = None,
) -> Sums:
    """Fold the traced elements round by round; each ray's sums end at its last element.

    With measured ``intensity``, each element's range density is multiplied by its intensity density.
    With a list ``shares``, every round appends its entries' :meth:`Sums.terms` to it.
    """
    out = [dr.select(rounds.none, v, 0.0) for v in (sums.log_mix, sums.log_pass, sums.log_lost)]
    running = sums
    for r in rounds.rounds:
        seg, sub = round_segment(table, model, rays, r)
        seg = model.segment_law(seg, sub)
        z_entry = dr.gather(mi.Float, z, r.ray)
        if r.log_density is not None:  # censored when cached (trace.cache_distributions)
            log_f, drop = r.log_density, r.drop
        else:
            drop, log_f = model.censor(seg, _entry_log_density(model, table, seg, z_entry, sub), sub)
        if intensity is not None:
            measured = dr.gather(mi.Float, intensity, r.ray)
            known = dr.isfinite(measured)
            log_f = log_f + dr.select(known, model.intensity.log_prob(seg, dr.select(known, measured, 0.0), sub), 0.0)
        before = running.gather(r.prev)
        if shares is not None:
            shares.append(before.terms(seg.p, drop, log_f))
        running = before.fold(seg.valid, seg.p, drop, log_f)
        values = (running.log_mix, running.log_pass, running.log_lost)
        out = [_add_at(o, v, r.ray, r.last) for o, v in zip(out, values)]
    return Sums(*out)


ESCAPED = -1  # ElementShares: the beam passed every traced element (the density's escape law, or a miss)
VIRTUAL = -2  # ElementShares: a virtual element of an effect (outliers, clutter) explains it best


@dataclass
class ElementShares:
    """What each element contributes to each ray's outcome: one row per (ray, element) met.

    Attributes:
        ray: (M,) the ray of each row.
        round: (M,) the element's round, or :data:`ESCAPED` or :data:`VIRTUAL`.
        entry: (M,) the element's entry in its round (-1 for :data:`ESCAPED` and :data:`VIRTUAL`).
        log_joint: (M,) log of the element's share of the outcome: ``log pi_k p_k (1 - drop_k) f_k(z)``
            for a return at ``z``, ``log pi_k p_k drop_k`` for a miss (-inf: it cannot have produced it).
        rays: number of rays.
    """

    ray: np.ndarray
    round: np.ndarray
    entry: np.ndarray
    log_joint: np.ndarray
    rays: int

    def credited(
        self, most_likely: bool = False, least: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(ray, round, entry, share)`` (M',) each, for fitting a density on the credited outcomes (the M step):
        the rows of a traced element or the escape state with a posterior share above ``least``
        (:meth:`posterior`; a ray's rows sum to 1 less what the effects' virtual elements, e.g. outliers,
        explain), or with ``most_likely`` each ray's row of the largest share, whole (rays a virtual element
        explains best are left out).
        """
        if most_likely:
            _, _, first = self._largest()
            first = first[self.round[first] != VIRTUAL]
            return self.ray[first], self.round[first], self.entry[first], np.ones(first.size)
        share = self.posterior()
        keep = (share > least) & (self.round != VIRTUAL)
        return self.ray[keep], self.round[keep], self.entry[keep], share[keep]

    def posterior(self) -> np.ndarray:
        """(M,) each row's posterior share of its ray's outcome (the E step of an EM; a ray's rows sum to 1).
        A ray none of whose elements can have produced its outcome is given wholly to its first row."""
        value, best, first = self._largest()
        finite = np.isfinite(best[self.ray])
        weight = np.where(finite, np.exp(value - np.where(finite, best[self.ray], 0.0)), 0.0)
        total = np.zeros(self.rays)
        np.add.at(total, self.ray, weight)
        weight = np.divide(weight, total[self.ray], out=np.zeros_like(weight), where=total[self.ray] > 0)
        weight[first[total <= 0]] = 1.0  # no finite share: every row is largest, the first is its first row
        return weight

    def _largest(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(value, best, first)``: the rows' log shares with NaN as -inf (M,), each ray's largest (B,), and the
        first row holding it (B,; every ray has rows, its virtual and escaped ones)."""
        value = np.where(np.isnan(self.log_joint), -np.inf, self.log_joint)
        best = np.full(self.rays, -np.inf)
        np.maximum.at(best, self.ray, value)
        first = np.full(self.rays, self.ray.size)
        rows = np.flatnonzero(value == best[self.ray])
        np.minimum.at(first, self.ray[rows], rows)
        return value, best, first


def element_shares(table, model, rays: RayBatch, rounds: Rounds, measured: mi.Float, hit: mi.Bool) -> ElementShares:
    """Every element's share of what the sensor reported, ray by ray: the E step of an EM over the pass-through mixture.

    A return at ``z`` gives element k the share ``pi_k p_k (1 - drop_k) f_k(z)``, a miss
    ``pi_k p_k drop_k``; the beam that passes every traced element (``pi_{K+1}``, then the density's
    escape law) and the effects' virtual elements (one row, :data:`VIRTUAL`) compete with them.
    Rows come in the order virtual (every ray), escaped (every ray), then round by round.

    Args:
        table, model, rays, rounds, measured, hit: as for :func:`mixture_log_likelihood` (compact
            :class:`Rounds` of single beams: no footprint effect, no cached batch).
    """
    rays = model.prepare_rays(rays)
    if model.fan_out(rays) is not None or not isinstance(rounds, Rounds):
        raise ParameterError("returns are credited to elements on traced rounds of single beams only")
    z = dr.select(hit, measured, 0.0)
    returned = np.asarray(hit, bool)
    sums = _fold_virtual(model, rays, z)
    every = np.arange(rays.width)
    virtual = np.where(returned, np.asarray(sums.log_mix, np.float64), np.asarray(sums.log_lost, np.float64))
    shares: list = []
    sums = _fold_rounds(table, model, rays, rounds, z, sums, shares=shares)
    escape = _escape_law(model, rays, z)
    if escape is None:
        term, lost = dr.full(mi.Float, -dr.inf, rays.width), sums.log_pass
    else:
        term, lost = sums.terms(*escape[1:])
    dr.eval(term, lost, shares)  # one kernel for every round, not one per conversion below
    parts = [(every, np.full(rays.width, VIRTUAL), np.full(rays.width, -1), virtual)]
    candidates = [(ESCAPED, every, term, lost)]
    candidates += [(k, np.asarray(r.ray, np.int64), *pair) for k, (r, pair) in enumerate(zip(rounds.rounds, shares))]
    for k, lanes, term, lost in candidates:
        value = np.where(returned[lanes], np.asarray(term, np.float64), np.asarray(lost, np.float64))
        entry = np.full(lanes.size, -1) if k == ESCAPED else np.arange(lanes.size)
        parts.append((lanes, np.full(lanes.size, k), entry, value))
    ray, round_of, entry, log_joint = (np.concatenate(column) for column in zip(*parts))
    return ElementShares(ray, round_of, entry, log_joint, rays.width)


def _fold_cached(table, model, rays: RayBatch, batch: CachedBatch, z: mi.Float, sums: Sums) -> Sums:
    """Fold the cached entries ray by ray: one unrolled kernel, entries read from the cache."""
    cache = batch.cache
    for k in range(cache.max_count):
        active = batch.count > k
        entry = batch.start + k

        def read(array, entry=entry, active=active):
            return dr.gather(type(array), array, entry, active)

        element = read(cache.element)
        if cache.log_density is not None:  # only the hit probabilities move
            p, drop, log_f = (
                dr.gather(mi.Float, table.p_hit, element, active),
                read(cache.drop),
                read(cache.log_density),
            )
        else:
            view = Round(
                ray=None,
                prev=None,
                last=None,
                element=element,
                nominal=read(cache.nominal),
                cos_incidence=read(cache.cos_incidence),
                point=None,
                normal=None,
                cached=tuple(read(a) for a in cache.cached or ()),
            )
            seg = model.segment_law(table.cached_segment(view, active, model.range_sigma), rays)
            p = seg.p
            drop, log_f = model.censor(seg, model.density.log_prob(seg, z, rays), rays)
        sums = sums.fold(active, p, drop, log_f)
    return sums


def _footprint_log_likelihood(table, model, fan, rounds: Rounds, measured: mi.Float, hit: mi.Bool) -> mi.Float:
    """Log-likelihood of beams fanned out into sub-rays, from the sub-rays' return moments."""
    effect, sub, weight = fan
    n = dr.width(hit)
    m = sub.width
    moments = SubRayMoments(
        log_miss=dr.zeros(mi.Float, m),
        p_return=dr.zeros(mi.Float, m),
        mean=dr.zeros(mi.Float, m),
        variance=dr.zeros(mi.Float, m),
    )
    log_pass = dr.zeros(mi.Float, m)
    for seg in model.virtual_segments(sub):
        moments, log_pass = _moment_step(moments, log_pass, model.segment_law(seg, sub, virtual=True), None, None)
    for r in rounds.rounds:
        seg, entry_rays = round_segment(table, model, sub, r)
        moments, log_pass = _moment_step(moments, log_pass, model.segment_law(seg, entry_rays), r.ray, r.prev)
    moments.log_miss = dr.log(dr.clip(1.0 - moments.p_return, TINY, 1.0))
    return effect.combine_log_likelihood(moments, weight, measured, hit, n, (model.min_range, model.max_range))


def _moment_step(moments: SubRayMoments, log_pass: mi.Float, seg: Segment, lanes, prev):
    """Add one element to each sub-ray's return probability and range moments (untruncated Gaussians).

    ``lanes`` are the sub-rays of a compact round (None: full width); ``log_pass`` is kept per
    sub-ray at full width, so ``prev`` is not needed.
    """
    reach = log_pass if lanes is None else dr.gather(mi.Float, log_pass, lanes)
    weight = dr.select(seg.valid, dr.exp(reach) * seg.p * (1.0 - seg.drop), 0.0)
    passed = reach + dr.select(seg.valid, dr.log(dr.clip(1.0 - seg.p, TINY, 1.0)), 0.0)
    mean, variance = range_moments(seg)
    state = (moments.p_return, moments.mean, moments.variance)
    if lanes is None:
        return SubRayMoments(moments.log_miss, *_merge_moments(state, (weight, mean, variance))), passed
    merged = _merge_moments(tuple(dr.gather(mi.Float, a, lanes) for a in state), (weight, mean, variance))
    new = [mi.Float(a) for a in state]
    for target, value in zip(new, merged):
        dr.scatter(target, value, lanes)
    log_pass = mi.Float(log_pass)
    dr.scatter(log_pass, passed, lanes)
    return SubRayMoments(moments.log_miss, *new), log_pass


def _merge_moments(mixture: tuple, component: tuple) -> tuple[mi.Float, mi.Float, mi.Float]:
    """Weight, mean (m) and variance (m^2) of the mixture ``(p, mean, variance)`` with ``component`` ``(w, m, s2)``.

    The pairwise update of Chan, Golub and LeVeque (1979): the new mean moves by a share of the difference
    and the variance gains that share's spread, so nothing is squared at the range's scale.
    """
    (p, mean, variance), (w, m, s2) = mixture, component
    total = p + w
    share = w / dr.maximum(total, 1e-30)
    delta = m - mean
    return total, mean + share * delta, (1.0 - share) * variance + share * (s2 + (1.0 - share) * dr.square(delta))
