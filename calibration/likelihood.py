"""The pass-through mixture on compact trace records, with gradients.

Along each ray the elements ``k = 1..K`` return with probability ``P_k = p_k prod_{j<k}(1 - p_j)``;
the log-likelihood of a measured return ``z`` is ``log sum_k P_k f_k(z)`` and that of a miss
``log prod_k (1 - p_k)`` (the same mixture as
:meth:`mi_lidar.core.sensor_model.SensorModel.log_likelihood`, with the same numerics). Here it is
evaluated on :class:`~mi_lidar.calibration.records.Rounds`: each round works only on the rays that
met an element in it and reads the running sums of its rays from the previous round (``prev``);
a ray's value is written when its last element has been folded in. A table with ``smoothing > 0``
scores its ellipsoids with the fitting-only surrogate of :mod:`~mi_lidar.calibration.smoothing`.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.calibration.records import CachedBatch, Round, Rounds
from mi_lidar.calibration.smoothing import smoothed_log_density
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import ELLIPSOID, Segment, log_density
from mi_lidar.core.sensor_model import SensorModel


def round_segment(table, model: SensorModel, rays: RayBatch, r: Round) -> tuple[Segment, RayBatch]:
    """The segments of round ``r`` with the effects applied, and the rays of its entries.

    Args:
        table: the :class:`~mi_lidar.calibration.differentiable.DiffTable` (may carry gradients).
        model: the sensor model (its effects may carry gradients).
        rays: the batch after :meth:`SensorModel.prepare_rays`.
        r: the round.

    Returns:
        One lane per entry: the :class:`Segment` (from ``r.cached`` when present, else rebuilt from
        the table's geometry along the entry's ray) after every effect's ``modify_segment``, and
        the entries' rays.
    """
    sub = rays.take(r.ray)
    valid = dr.full(mi.Bool, True, r.width)
    if r.cached is None:
        seg = table.segment(r, valid, r.element, sub.origin, sub.direction, model.range_sigma)
    else:
        seg = table.cached_segment(r.element, r.nominal, r.cos_incidence, r.cached, model.range_sigma, valid)
    return model.apply_effects(seg, sub), sub


def _fold(
    log_pass: mi.Float, log_mix: mi.Float, valid: mi.Bool, p: mi.Float, density: mi.Float
) -> tuple[mi.Float, mi.Float]:
    """Add one element to the running ``log prod(1 - p_j)`` and ``log sum P_k f_k(z)`` (nats).

    Args:
        log_pass, log_mix: the running sums.
        valid: lanes that met the element.
        p: its hit probability.
        density: log density (1/m) of the measured range under its return distribution.
    """
    term = dr.select(valid, log_pass + dr.log(dr.clip(p, 1e-12, 1.0)) + density, -dr.inf)
    high = dr.maximum(log_mix, term)
    safe = dr.select(dr.isinf(high), 0.0, high)
    log_mix = dr.select(dr.isinf(high), high, safe + dr.log(dr.exp(log_mix - safe) + dr.exp(term - safe)))
    log_pass = log_pass + dr.select(valid, dr.log(dr.maximum(1.0 - p, 1e-12)), 0.0)
    return log_pass, log_mix


def mixture_log_likelihood(
    table, model: SensorModel, rays: RayBatch, rounds: Rounds, measured: mi.Float, hit: mi.Bool
) -> mi.Float:
    """Per-ray log-likelihood (nats) of measured ranges under the pass-through mixture.

    Args:
        table: the element table (its arrays may carry gradients).
        model: the sensor model (virtual elements of its effects come first along every ray).
        rays: the batch the rounds were traced for (world frame, before ray perturbations).
        rounds: its records: compact :class:`Rounds`, or a :class:`CachedBatch` of cached rays.
        measured: (B,) measured ranges, m (ignored where ``hit`` is False).
        hit: (B,) True where the sensor reported a return.

    Returns:
        (B,) ``log sum_k P_k f_k(z)`` for returns and ``log prod_k (1 - p_k)`` for misses.
    """
    rays = model.prepare_rays(rays)
    n = rounds.width
    z = dr.select(hit, measured, 0.0)
    log_pass, log_mix = dr.zeros(mi.Float, n), dr.full(mi.Float, -dr.inf, n)
    for seg in model.virtual_segments(rays):
        seg = model.likelihood_segment(seg, rays)
        log_pass, log_mix = _fold(log_pass, log_mix, seg.valid, seg.p, log_density(seg, z))
    if isinstance(rounds, CachedBatch):
        # ---------------- Ray by ray: one unrolled kernel, entries read from the cache ----------
        cache = rounds.cache
        for k in range(cache.max_count):
            active = rounds.count > k
            entry = rounds.start + k
            read = lambda array, entry=entry, active=active: dr.gather(type(array), array, entry, active)
            element = read(cache.element)
            if cache.log_density is not None:  # only the hit probabilities move
                p, density = dr.gather(mi.Float, table.p_hit, element, active), read(cache.log_density)
            else:
                seg = table.cached_segment(
                    element,
                    read(cache.nominal),
                    read(cache.cos_incidence),
                    tuple(read(a) for a in cache.cached),
                    model.range_sigma,
                    active,
                )
                seg = model.likelihood_segment(model.apply_effects(seg, rays), rays)
                p, density = seg.p, log_density(seg, z)
            log_pass, log_mix = _fold(log_pass, log_mix, active, p, density)
        return dr.select(hit, log_mix, log_pass)
    # ---------------- Round by round: each round reads its rays' running sums at `prev` ---------
    ll = dr.select(rounds.none, dr.select(hit, log_mix, log_pass), 0.0)
    for r in rounds.rounds:
        seg, sub = round_segment(table, model, rays, r)
        seg = model.likelihood_segment(seg, sub)
        z_entry = dr.gather(mi.Float, z, r.ray)
        density = (
            smoothed_log_density(seg, z_entry, table.smoothing) if table.smoothing > 0 else log_density(seg, z_entry)
        )
        log_pass, log_mix = _fold(_previous(log_pass, r.prev), _previous(log_mix, r.prev), seg.valid, seg.p, density)
        value = dr.select(dr.gather(mi.Bool, hit, r.ray), log_mix, log_pass)
        ll = _add_at(ll, value, r.ray, r.last)
    return ll


def _previous(running: mi.Float, prev: mi.UInt32) -> mi.Float:
    """The previous round's running sums ``running`` (nats) read at ``prev``, with gradients.

    The indices of a round are distinct, so the gather's derivative (a scatter-add into an array
    as long as the previous round) is compiled without conflict handling. Dr.Jit's default mode on
    the LLVM backend would expand the target per thread and write its length into the kernel as a
    constant; that length changes with every batch of rays, so the backward kernel of every round
    would be compiled anew at every step of a geometry fit.
    """
    return dr.gather(mi.Float, running, prev, mode=dr.ReduceMode.NoConflicts)


def _add_at(target: mi.Float, value: mi.Float, index: mi.UInt32, active: mi.Bool) -> mi.Float:
    """``target`` plus ``value`` scattered (added) to lanes ``index`` where ``active`` (keeps gradients)."""
    out = mi.Float(target)
    dr.scatter_reduce(dr.ReduceOp.Add, out, value, index, active)
    return out


def returned_and_passed(seg: Segment, z: mi.Float, hit: mi.Bool, gate: float) -> tuple[mi.Bool, mi.Bool]:
    """Counting rule of one element: did it return the measured range, or let the ray pass?

    A return counts as the element's when ``z`` lies in its chord (ellipsoids) or within ``gate``
    sigmas of its mean (surfaces); the ray passed the element when it missed or returned beyond.
    """
    ellipsoid = seg.kind == ELLIPSOID
    upper = dr.select(ellipsoid, seg.hi, seg.mean + gate * seg.sigma)
    lower = dr.select(ellipsoid, seg.lo, seg.mean - gate * seg.sigma)
    returned = hit & (z >= lower) & (z <= upper)
    return returned, ~returned & (~hit | (z > upper))
