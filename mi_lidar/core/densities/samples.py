"""Learned densities' training data: per ray, the state of the element credited with its outcome, and the measurement.

Learned densities (P-Reg, NP-Reg, the binned baselines) condition on the state of the element a
beam meets. :class:`StateSamples` holds, per ray (numpy), the nominal range and incidence of one
element on the ray (NaN nominal for the escape state: the ray met nothing, or passed everything),
its beam and label, and the measured return. By default that element is the ray's *first*, which
is exact for scenes of opaque surfaces; with permeable elements a return may come from an element
behind it, and the caller shares each ray's outcome among the elements that could have produced it by
their posterior (:meth:`~mi_lidar.core.likelihood.ElementShares.credited`: the EM of ``fit-sensor``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from mi_lidar.core.errors import ParameterError


@dataclass
class StateSamples:
    """Per-sample states and measurements (all arrays (N,), numpy; a sample is a ray, or a share of a ray's
    outcome credited to one element).

    Attributes:
        nominal: nominal range of the first element, m (NaN: the ray met nothing).
        incidence: incidence angle at it, deg (NaN: unknown).
        beam: beam index.
        label: class label of the element (0 where none).
        z: measured range, m (NaN for a miss).
        hit: True where the sensor reported a return.
        weight: what the sample counts for in a fit, e.g. its share of its ray's outcome (default 1: the whole ray).
    """

    nominal: np.ndarray
    incidence: np.ndarray
    beam: np.ndarray
    label: np.ndarray
    z: np.ndarray
    hit: np.ndarray
    weight: np.ndarray | None = field(default=None)

    def __post_init__(self):
        if self.weight is None:
            self.weight = np.ones(np.shape(self.hit))
        sizes = {f.name: np.shape(getattr(self, f.name)) for f in fields(self)}
        if len(set(sizes.values())) != 1:
            raise ParameterError(f"state samples: arrays of different shapes {sizes}; give one value per ray")

    @property
    def n(self) -> int:
        return int(self.hit.size)

    @property
    def met(self) -> np.ndarray:
        """True where the ray met an element."""
        return np.isfinite(self.nominal)

    @property
    def residual(self) -> np.ndarray:
        """``z - nominal`` (m; NaN for misses and escaped rays)."""
        return self.z - self.nominal

    def take(self, mask: np.ndarray) -> StateSamples:
        """The samples where ``mask`` (bool or index array)."""
        return StateSamples(*(getattr(self, f.name)[mask] for f in fields(self)))

    @classmethod
    def from_rounds(
        cls,
        rounds,
        beam: np.ndarray,
        label_of_element: np.ndarray,
        z: np.ndarray,
        hit: np.ndarray,
        credited: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> StateSamples:
        """The states of the elements of a trace (:class:`~mi_lidar.core.trace.Rounds`) credited with the outcomes.

        Args:
            rounds: the trace of N rays (one lane per ray, no fan-out).
            beam: (N,) beam index of each ray.
            label_of_element: (E_total,) label of every element of the table.
            z: (N,) measured ranges, m (ignored where not ``hit``).
            hit: (N,) return flags.
            credited: ``(ray, round, entry, share)`` (M,) each: one sample per row, the state of entry
                ``entry`` of round ``round`` (a negative round: the escape state) with ray ``ray``'s
                measurement, counted with weight ``share``
                (:meth:`~mi_lidar.core.likelihood.ElementShares.credited`, the E step of ``fit-sensor``'s EM);
                None: the first element of every ray, whole.
        """
        if credited is None:
            n = rounds.width
            round_of, entry_of = np.full(n, -1), np.full(n, -1)
            if rounds.rounds:
                lanes = np.asarray(rounds.rounds[0].ray, np.int64)
                round_of[lanes], entry_of[lanes] = 0, np.arange(lanes.size)
            credited = (np.arange(n), round_of, entry_of, np.ones(n))
        ray, round_of, entry_of, share = credited
        nominal = np.full(ray.size, np.nan)
        incidence = np.full(ray.size, np.nan)
        label = np.zeros(ray.size, np.int64)
        for k, entries in enumerate(rounds.rounds):
            rows = np.flatnonzero(round_of == k)
            if rows.size == 0:
                continue
            at = entry_of[rows]
            nominal[rows] = np.asarray(entries.nominal, np.float64)[at]
            cos = np.clip(np.asarray(entries.cos_incidence, np.float64)[at], 0.0, 1.0)
            incidence[rows] = np.degrees(np.arccos(cos))
            label[rows] = np.asarray(label_of_element)[np.asarray(entries.element, np.int64)[at]]
        hit = np.asarray(hit, bool)[ray]
        return cls(
            nominal=nominal,
            incidence=incidence,
            beam=np.asarray(beam, np.int64)[ray],
            label=label,
            z=np.where(hit, np.asarray(z, np.float64)[ray], np.nan),
            hit=hit,
            weight=np.asarray(share, np.float64),
        )


def protocol_residual_edges(reach: float = 82.0) -> np.ndarray:
    """Residual bin edges (m) of the real-planar protocol: 1 cm within 0.3 m, 2 cm to 1 m, 10 cm to 5 m, 1 m beyond.

    Symmetric about 0 and out to ``reach`` m on both sides (the sensor's maximum range, so that any
    return of a nominal-miss ray, whose residual is its range, falls in a bin).
    """
    pieces = [
        np.arange(0.0, 0.3, 0.01),
        np.arange(0.3, 1.0, 0.02),
        np.arange(1.0, 5.0, 0.1),
        np.arange(5.0, math.ceil(reach) + 1.0, 1.0),
    ]
    positive = np.unique(np.round(np.concatenate(pieces), 6))
    return np.concatenate([-positive[:0:-1], positive])


def choose_by_held_out(candidates: list, build, held_out_score, progress=None) -> tuple:
    """The candidate settings whose density scores best held out.

    Args:
        candidates: settings (tuples).
        build: ``build(*setting) -> density``.
        held_out_score: mean held-out NLL (nats per ray) of a density (the one likelihood).
        progress: optional ``progress(done, total)``.

    Returns:
        ``(best density, [(*setting, NLL), ...])``.
    """
    table: list = []
    best: tuple | None = None
    for i, setting in enumerate(candidates):
        density = build(*setting)
        nll = float(held_out_score(density))
        table.append((*setting, nll))
        if best is None or nll < best[0]:
            best = (nll, density)
        if progress is not None:
            progress(i + 1, len(candidates))
    if best is None:
        raise ParameterError("no candidate settings to choose from")
    return best[1], table


def choose_then_vary(candidates: list, stages, build, held_out_score, progress=None) -> tuple:
    """:func:`choose_by_held_out` over ``candidates``, then stage by stage over ``stage(chosen setting)``:
    settings that change the setting chosen so far in what the earlier stages held fixed (each tried with
    everything else as chosen).

    Args:
        candidates: settings (tuples) of the first stage.
        stages: functions ``stage(setting) -> [setting, ...]``, in order (the progress total counts what each
            returns for the first candidate).
        build, held_out_score, progress: as for :func:`choose_by_held_out` (progress over every stage).

    Returns:
        ``(best density of every stage, [(*setting, NLL), ...] of every stage)``.
    """
    total = len(candidates) + sum(len(stage(candidates[0])) for stage in stages) if candidates else 0
    done = 0

    def step(finished: int, _total: int) -> None:
        if progress is not None:
            progress(done + finished, total)

    best, table = choose_by_held_out(candidates, build, held_out_score, step)
    done += len(candidates)
    for stage in stages:
        *chosen, best_nll = min(table, key=lambda row: row[-1])
        others = stage(tuple(chosen))
        if not others:
            continue
        other, rows = choose_by_held_out(others, build, held_out_score, step)
        done += len(others)
        table += rows
        if min(row[-1] for row in rows) < best_nll:
            best = other
    return best, table
