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

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from mi_lidar.planar.mixture import BeamMixture, fit_shares, mix_raw
from mi_lidar.planar.trace import PlanarTrace

ANGULAR_STREAM = 4  # the random stream that picks an angular part (the sampler's are 0-3 and 64 up)
OFFSETS = (-1, 1)  # the neighbours, in beam spacings
PART_GROUPS = (0, 1, 1, 2, 2)  # the own trace; the neighbours alone, alike; the footprints, alike


@dataclass
class AngularMixture(BeamMixture):
    """Beams whose return comes from their own trace, a neighbour's alone, or their footprint (module docstring),
    under one model: the mixture of the five pass-through likelihoods, scored once by the one score; sampling
    picks one part (stream :data:`ANGULAR_STREAM`), then samples it (:class:`~mi_lidar.planar.mixture.BeamMixture`).

    Attributes:
        parts: the beams of the own trace, of the neighbours -1 and +1 alone, then of the footprints over
            -1 and +1 (each with the measured returns of the beams themselves).
        weight: the share of each neighbour alone.
        footprint: the share of each footprint (``2 weight + 2 footprint <= 1``).
    """

    weight: float
    footprint: float = 0.0
    STREAM: ClassVar[int] = ANGULAR_STREAM

    def shares(self) -> np.ndarray:
        """(5,) probability of each part."""
        return part_shares(self.weight, self.footprint)


def part_shares(weight: float, footprint: float) -> np.ndarray:
    """(5,) probability of each part of an :class:`AngularMixture` with these shares."""
    return np.array([1.0 - 2.0 * weight - 2.0 * footprint, weight, weight, footprint, footprint])


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
    """The shares ``(weight, footprint)`` that maximise the mean one score of (5, B) raw part log-likelihoods
    (:func:`~mi_lidar.planar.mixture.fit_shares`, the two neighbours' parts of a kind alike); ``(0, 0)``, no
    spread, when no beam tells the parts apart."""
    shares = fit_shares(raw, hit, PART_GROUPS, part_shares(0.05, 0.05), uninformed=part_shares(0.0, 0.0))
    return float(shares[1]), float(shares[3])
