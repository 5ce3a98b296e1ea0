"""A planar beam's angular spread: its return comes from its own trace, a neighbour's, or the nearer of the two.

A real beam is not a line: it diverges, and the pose it was fired from carries a heading error. Where
the scene changes within a beam spacing (a door frame, a table leg, a wall's end) the return comes from
either side. The spread is discretised at the scan's own beam spacing, in five parts
(:class:`AngularMixture`), all seen from the same pose through the same leave-out map:

* the beam's own trace;
* the trace of beam ``i - 1`` or ``i + 1`` alone (:meth:`~mi_lidar.planar.trace.PlanarTrace.shifted`,
  share ``weight`` each): the whole beam turned by a heading error;
* the beam's *footprint* over beam ``i - 1``'s or ``i + 1``'s direction
  (:meth:`~mi_lidar.planar.trace.PlanarTrace.footprint`, share ``footprint`` each): both directions'
  segments in range order, so the nearer surface returns. A diverging beam that half meets a post
  reports the post, never the wall behind it.

Why both kinds: with the neighbours alone, the Edmonton fit (Freiburg's untuned log, 2026-11-28)
drew 6.9 % of its sampled test returns more than 1 m behind a beam's first wall, where the sensor gave
4.9 %: where a neighbour's trace passes an edge that stops the beam's own, the neighbour's far return
was drawn. With both kinds, each share fitted (0.074 alone, 0.071 footprint), the test NLL was the same
(4.1564 -> 4.1566), 6.1 % of the sampled returns lay that far, and the histogram match of sampled test
scans fell 0.243 -> 0.094 m (mean of six independent draws); on Intel and the Freiburg campus (footprint
shares 0.005 and 0.012) the NLL and the samples were unchanged. With the footprints alone the test NLL
rose 0.013 on Edmonton and 0.015 on Intel.

Every beam has its footprints, also where both directions meet the same wall: the wall's two cells
then both intercept, so a footprint passes a thin wall less often than one direction does. Built only
where the two first walls differ by more than 0.5 m (the own trace elsewhere), the footprints took
share 0.111 on Edmonton, scored 4.1485, and the histogram match was 0.179 m: the beams that pass a
wall drew more far returns. The footprints hold every segment twice, so the mixture holds each
segment seven times instead of three (on Edmonton the fit took 101 s where it took 82 s, both run side by
side).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_lidar.core.likelihood import LOG_FLOOR, LOG_RESOLUTION
from mi_lidar.core.streams import BeamCorrelation, NeighbourStreams, uniform
from mi_lidar.planar.beams import EngineBeams, scored
from mi_lidar.planar.trace import PlanarTrace

ANGULAR_STREAM = 4  # the random stream that picks an angular part (the sampler's are 0-3 and 64 up)
OFFSETS = (-1, 1)  # the neighbours, in beam spacings
SHARE_TOLERANCE = 1e-6  # the shares' fit has converged when no share moves by more
SHARE_ROUNDS = 500  # at most this many rounds of the shares' fit
MAX_EXPONENT = 700.0  # a beam far below the floor under every part keeps a finite floor (its posteriors ~0)


@dataclass
class AngularMixture:
    """Beams whose return comes from their own trace, a neighbour's alone, or their footprint (module docstring).

    Its likelihood is the mixture of the five pass-through likelihoods, scored once by the one score;
    sampling picks one part, then samples it.

    Attributes:
        parts: the beams of the own trace, of the neighbours -1 and +1 alone, then of the footprints over
            -1 and +1 (each with the measured returns of the beams themselves).
        weight: the share of each neighbour alone.
        footprint: the share of each footprint (``2 weight + 2 footprint <= 1``).
    """

    parts: tuple[EngineBeams, ...]
    weight: float
    footprint: float = 0.0

    @property
    def n(self) -> int:
        return self.parts[0].n

    @property
    def hit(self) -> np.ndarray:
        return np.asarray(self.parts[0].hit)

    def shares(self) -> np.ndarray:
        """(5,) probability of each part."""
        return part_shares(self.weight, self.footprint)

    def raw_parts(self, model) -> np.ndarray:
        """(5, B) raw log-likelihood of every part (nats)."""
        return np.stack([b.raw_log_likelihood(model) for b in self.parts])

    def raw_log_likelihood(self, model) -> np.ndarray:
        """(B,) raw log-likelihood of the mixture (nats)."""
        return mix_raw(self.raw_parts(model), self.shares())

    def log_likelihood(self, model) -> np.ndarray:
        """(B,) scored log-likelihood per beam (nats)."""
        return scored(self.raw_log_likelihood(model), self.hit)

    def p_miss(self, model) -> np.ndarray:
        """(B,) probability of no return per beam."""
        return np.tensordot(self.shares(), np.stack([b.p_miss(model) for b in self.parts]), axes=1)

    def with_correlation(self, correlation: BeamCorrelation) -> AngularMixture:
        """These beams with every part sampled with ``correlation``."""
        parts = tuple(dataclasses.replace(b, correlation=correlation) for b in self.parts)
        return dataclasses.replace(self, parts=parts)

    def streams(self, seed: int, follows: np.ndarray | None = None) -> int | NeighbourStreams:
        """The random streams of a sample with ``seed`` (:meth:`EngineBeams.streams`; the parts' beams are the same)."""
        return self.parts[0].streams(seed, follows)

    def numbered_from(self, first: int) -> AngularMixture:
        """These beams as rays ``first ..`` of a larger set (:meth:`EngineBeams.numbered_from`)."""
        parts = tuple(b.numbered_from(first) for b in self.parts)
        return dataclasses.replace(self, parts=parts)

    def sample(self, model, seed: int | NeighbourStreams = 0) -> tuple[np.ndarray, np.ndarray]:
        """One sampled (range, hit) per beam: the part drawn by its share, then that part's sample.

        The parts draw from the same random streams (``seed``'s, or the streams given), so a beam keeps its
        share of its neighbours' errors whichever part it reports. The part is picked by a stream of its own
        (:data:`ANGULAR_STREAM`, independent of the others), keyed like them by the ray id; each part draws
        only the beams that picked it.
        """
        streams = seed if isinstance(seed, NeighbourStreams) else self.streams(seed)
        key = streams.seed if isinstance(streams, NeighbourStreams) else streams
        with dr.suspend_grad():
            u = np.asarray(uniform(key, self.parts[0].rays.ray_id, 0, ANGULAR_STREAM), np.float64)
        part = np.searchsorted(np.cumsum(self.shares())[:-1], u, side="right")
        z, hit = np.full(self.n, np.nan), np.zeros(self.n, bool)
        for k in np.unique(part):
            picked = part == k
            z_k, hit_k = self.parts[k].sample(model, streams, picked)
            z[picked], hit[picked] = z_k[picked], hit_k[picked]
        return z, hit


def part_shares(weight: float, footprint: float) -> np.ndarray:
    """(5,) probability of each part of an :class:`AngularMixture` with these shares."""
    return np.array([1.0 - 2.0 * weight - 2.0 * footprint, weight, weight, footprint, footprint])


def mix_raw(raw: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """(B,) ``log sum_k shares_k exp(raw_k)`` of (K, B) raw log-likelihoods (parts of zero share left out)."""
    used = shares > 0
    return np.logaddexp.reduce(raw[used] + np.log(shares[used])[:, None], axis=0)


def own_part_posterior(raw: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """(B,) each beam's posterior probability that its outcome came from its own trace (part 0), from (K, B) raw
    part log-likelihoods and (K,) ``shares``.

    Among the parts alone, not against the score's floor: an outcome that no part explains still counts in
    full (its share, where every part gives it probability 0), as the E step over segments counts every outcome;
    with the floor as a part, the rarest returns would lose weight in the tables at every step.
    """
    log_mix = mix_raw(raw, shares)
    explained = np.isfinite(log_mix)
    own = np.full(raw.shape[1], shares[0])
    own[explained] = np.exp(raw[0, explained] + np.log(shares[0]) - log_mix[explained])
    return own


def angular_mixture(trace: PlanarTrace, beams, weight: float, footprint: float = 0.0) -> AngularMixture:
    """The :class:`AngularMixture` of ``trace`` with shares ``weight`` and ``footprint``; ``beams(trace)``
    builds each part."""
    alone = tuple(beams(trace.shifted(k)) for k in OFFSETS)
    footprints = tuple(beams(trace.footprint(k)) for k in OFFSETS)
    return AngularMixture(parts=(beams(trace), *alone, *footprints), weight=weight, footprint=footprint)


def fit_angular_shares(raw: np.ndarray, hit: np.ndarray) -> tuple[float, float]:
    """The shares ``(weight, footprint)`` that maximise the mean one score of (5, B) raw part log-likelihoods.

    The score of a beam is ``log(sum_k s_k P_k + FLOOR)`` (:func:`~mi_lidar.core.likelihood.score`; ``P_k``
    the probability of its 1 cm bin or of its miss under part ``k``), so each round of this EM (a
    minorise-maximise step: the floor is a part of fixed weight) sets every share to the mean posterior
    of its parts, the two neighbours' parts of a kind together, and never lowers the score. It stops when
    no share moves by more than :data:`SHARE_TOLERANCE` (at most :data:`SHARE_ROUNDS` rounds). The score of a
    beam that every part explains alike does not depend on the shares: such beams are left out (none
    left: no spread, ``(0, 0)``).
    """
    log_p = raw + np.where(np.asarray(hit, bool), LOG_RESOLUTION, 0.0)[None]
    log_p = log_p[:, np.ptp(log_p, axis=0) > 0]
    if not log_p.shape[1]:
        return 0.0, 0.0
    top = log_p.max(axis=0)  # each beam's probabilities relative to its likeliest part's: in [0, 1]
    p = np.exp(log_p - top)
    floor = np.exp(np.minimum(LOG_FLOOR - top, MAX_EXPONENT))
    weight = footprint = 0.05
    for _ in range(SHARE_ROUNDS):
        shares = part_shares(weight, footprint)
        posterior = shares * (p @ (1.0 / (shares @ p + floor)))
        posterior /= posterior.sum()
        moved = (posterior[1] + posterior[2]) / 2.0, (posterior[3] + posterior[4]) / 2.0
        done = max(abs(moved[0] - weight), abs(moved[1] - footprint)) < SHARE_TOLERANCE
        weight, footprint = moved
        if done:
            break
    return float(weight), float(footprint)
