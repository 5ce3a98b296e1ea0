"""Beams whose outcome comes from one of several parts, by shares: the one mixture of planar beams.

Two models are such mixtures (:class:`BeamMixture`): a beam's angular spread
(:class:`~mi_lidar.planar.angular.AngularMixture`: its own trace, a neighbour's, or a footprint, under one
model) and mi-lidar's stacked maps (:class:`StackedBeams`: the same beams under two permeable maps fitted with
different labels, each its own model). Both score the mixture of the parts' likelihoods by the one score, and
sample by picking one part per beam, then sampling it; both fit their shares by :func:`fit_shares`.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import drjit as dr
import numpy as np

from mi_lidar.core.likelihood import LOG_FLOOR, LOG_RESOLUTION
from mi_lidar.core.streams import BeamCorrelation, NeighbourStreams, uniform
from mi_lidar.planar.beams import scored

SHARE_TOLERANCE = 1e-6  # the shares' fit has converged when no share moves by more
SHARE_ROUNDS = 500  # at most this many rounds of the shares' fit
MAX_EXPONENT = 700.0  # a beam far below the floor under every part keeps a finite floor (its posteriors ~0)
STACK_STREAM = 5  # the random stream that picks a stacked map (the sampler's are 0-3 and 64 up, the angular 4)


@dataclass
class BeamMixture(ABC):
    """Beams whose outcome comes from one of ``parts`` (beams of the same rays, each with its own measured
    outcome arrays equal) with the probabilities :meth:`shares`.

    Subclasses say what the shares are, which model scores each part (:meth:`part_models`) and which random
    stream picks the part (:attr:`STREAM`).
    """

    parts: tuple
    STREAM: ClassVar[int]

    @abstractmethod
    def shares(self) -> np.ndarray:
        """(K,) probability of each part."""

    def part_models(self, model) -> tuple:
        """The model each part is scored and sampled by: ``model`` for all of them."""
        return (model,) * len(self.parts)

    @property
    def n(self) -> int:
        return self.parts[0].n

    @property
    def hit(self) -> np.ndarray:
        return np.asarray(self.parts[0].hit)

    @property
    def ray_id(self):
        """The rays' ids (as numbered by :meth:`numbered_from`): they key every random stream."""
        return self.parts[0].ray_id

    def raw_parts(self, model) -> np.ndarray:
        """(K, B) raw log-likelihood of every part (nats)."""
        return np.stack([b.raw_log_likelihood(m) for b, m in zip(self.parts, self.part_models(model))])

    def raw_log_likelihood(self, model) -> np.ndarray:
        """(B,) raw log-likelihood of the mixture (nats)."""
        return mix_raw(self.raw_parts(model), self.shares())

    def log_likelihood(self, model) -> np.ndarray:
        """(B,) scored log-likelihood per beam (nats)."""
        return scored(self.raw_log_likelihood(model), self.hit)

    def p_miss(self, model) -> np.ndarray:
        """(B,) probability of no return per beam."""
        misses = [b.p_miss(m) for b, m in zip(self.parts, self.part_models(model))]
        return np.tensordot(self.shares(), np.stack(misses), axes=1)

    def with_correlation(self, correlation: BeamCorrelation) -> BeamMixture:
        """These beams with every part sampled with ``correlation``."""
        return dataclasses.replace(self, parts=tuple(b.with_correlation(correlation) for b in self.parts))

    def streams(self, seed: int, follows: np.ndarray | None = None) -> int | NeighbourStreams:
        """The random streams of a sample with ``seed`` (those of the parts' beams, which are the same)."""
        return self.parts[0].streams(seed, follows)

    def numbered_from(self, first: int) -> BeamMixture:
        """These beams as rays ``first ..`` of a larger set
        (:meth:`~mi_lidar.planar.beams.EngineBeams.numbered_from`)."""
        return dataclasses.replace(self, parts=tuple(b.numbered_from(first) for b in self.parts))

    def sample(
        self, model, seed: int | NeighbourStreams = 0, active: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """One sampled (range, hit) per beam: the part drawn by its share, then that part's sample.

        The parts draw from the same random streams (``seed``'s, or the streams given), so a beam keeps its
        share of its neighbours' errors whichever part it reports. The part is picked by a stream of its own
        (:attr:`STREAM`, independent of the others), keyed like them by the ray id; each part draws only the
        beams that picked it. ``active``: (B,) bool, only these beams draw (the others report a miss).
        """
        streams = seed if isinstance(seed, NeighbourStreams) else self.streams(seed)
        key = streams.seed if isinstance(streams, NeighbourStreams) else streams
        with dr.suspend_grad():
            u = np.asarray(uniform(key, self.ray_id, 0, self.STREAM), np.float64)
        part = np.searchsorted(np.cumsum(self.shares())[:-1], u, side="right")
        drawing = np.ones(self.n, bool) if active is None else np.asarray(active, bool)
        z, hit = np.full(self.n, np.nan), np.zeros(self.n, bool)
        for k, model_k in enumerate(self.part_models(model)):
            picked = (part == k) & drawing
            if picked.any():
                z_k, hit_k = self.parts[k].sample(model_k, streams, picked)
                z[picked], hit[picked] = z_k[picked], hit_k[picked]
        return z, hit


@dataclass
class StackedBeams(BeamMixture):
    """The same beams under several fitted maps, mixed by ``stack`` (stacking:
    :func:`~mi_lidar.planar.permeable.fit_milidar`); each part is scored and sampled by its own model, so the
    ``model`` this mixture takes is the tuple of them, in the parts' order.

    Attributes:
        stack: (K,) each map's share.
    """

    stack: np.ndarray
    STREAM: ClassVar[int] = STACK_STREAM

    def shares(self) -> np.ndarray:
        return np.asarray(self.stack, np.float64)

    def part_models(self, model) -> tuple:
        if len(model) != len(self.parts):
            raise ValueError(f"{len(self.parts)} stacked maps need as many models; got {len(model)}")
        return tuple(model)


def mix_raw(raw: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """(B,) ``log sum_k shares_k exp(raw_k)`` of (K, B) raw log-likelihoods (parts of zero share left out)."""
    used = shares > 0
    return np.logaddexp.reduce(raw[used] + np.log(shares[used])[:, None], axis=0)


def fit_shares(
    raw: np.ndarray, hit: np.ndarray, groups, start: np.ndarray, uninformed: np.ndarray | None = None
) -> np.ndarray:
    """(K,) shares of the parts that maximise the mean one score of their (K, B) raw log-likelihoods ``raw``.

    The score of a beam is ``log(sum_k s_k P_k + FLOOR)`` (:func:`~mi_lidar.core.likelihood.score`; ``P_k`` the
    probability of its 1 cm bin (``hit``) or of its miss under part ``k``), so each round of this EM (a
    minorise-maximise step: the floor is a part of fixed weight) sets every share to the mean posterior of its
    part, the parts of one group (``groups``: (K,) group of each part) to the mean over the group, and never
    lowers the score. The score is concave in the shares, so the fit reaches its maximum from any ``start``
    ((K,), positive, summing to 1; each group's parts alike). It stops when no share moves by more than
    :data:`SHARE_TOLERANCE` (at most :data:`SHARE_ROUNDS` rounds). A beam that every part explains alike does
    not move the score: such beams are left out, and with none left the result is ``uninformed`` (default
    ``start``).
    """
    log_p = raw + np.where(np.asarray(hit, bool), LOG_RESOLUTION, 0.0)[None]
    log_p = log_p[:, np.ptp(log_p, axis=0) > 0]
    shares = np.asarray(start, np.float64)
    if not log_p.shape[1]:
        return shares if uninformed is None else np.asarray(uninformed, np.float64)
    top = log_p.max(axis=0)  # each beam's probabilities relative to its likeliest part's: in [0, 1]
    p = np.exp(log_p - top)
    floor = np.exp(np.minimum(LOG_FLOOR - top, MAX_EXPONENT))
    groups = np.asarray(groups)
    size = np.bincount(groups)
    for _ in range(SHARE_ROUNDS):
        posterior = shares * (p @ (1.0 / (shares @ p + floor)))
        moved = (np.bincount(groups, posterior / posterior.sum()) / size)[groups]
        done = np.max(np.abs(moved - shares)) < SHARE_TOLERANCE
        shares = moved
        if done:
            break
    return shares
