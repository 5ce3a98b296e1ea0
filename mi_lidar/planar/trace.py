"""Traced planar beams: what the protocol's ray march found for every beam, in CSR form (:class:`PlanarTrace`).

The march itself is :mod:`mi_lidar.planar.raymarch`; here are the views the models take of its result:
a subset of beams, a beam's neighbour, the footprint over two directions, backstops behind the last cell.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

SEGMENT_FIELDS = (
    "seg_range",
    "seg_hits",
    "seg_passes",
    "seg_occupied",
    "seg_incidence",
    "seg_line_incidence",
    "seg_surface",
)
# seg_occupied, the occupancy class of a segment: 0 stray hits, 1 ``occ3`` occupied; after
# :meth:`PlanarTrace.with_backstops` also the classes below (a beam "in the open" meets no ``occ3`` cell)
BACKSTOP = 2  # the backstop of a beam that met an ``occ3`` cell
OPEN_BACKSTOP = 3  # the backstop of a beam in the open
OPEN_STRAY = 4  # a stray-hit cell on a beam in the open
OCCUPANCY_NAMES = ("stray_cells", "occupied_cells", "backstops", "open_backstops", "open_stray_cells")  # 0-4
BACKSTOP_DEPTH = 0.05  # m: a backstop lies one map cell behind a beam's last segment


@dataclass
class PlanarTrace:
    """Traced beams of a set of scans (per-beam arrays (B,), segments in CSR form).

    Attributes:
        scan, beam: indices of each beam.
        z: measured range, m (NaN for a miss).
        nominal: nominal range, m (NaN: nominal miss).
        incidence: incidence angle at the nominal hit, deg (NaN: unknown).
        seg_start: (B + 1,) offsets of each beam's segments.
        seg_range, seg_hits, seg_passes, seg_occupied: per segment (E,).
        seg_incidence: per segment (E,), the incidence (deg) on the surface in the cell, from the leave-out
            endpoint hits (:meth:`CellLines.surface_incidence`; NaN: unknown). Known more often than
            ``incidence``, which follows the protocol's rule.
        seg_line_incidence: per segment (E,), the incidence (deg) by the protocol's rule
            (:meth:`CellLines.incidence`; NaN: unknown), as ``incidence`` is for the nominal cell.
        seg_surface: per segment (E,), the range (m) of the surface in the cell along the beam, from
            the leave-out endpoint hits (:meth:`CellLines.surface_range`).
    """

    scan: np.ndarray
    beam: np.ndarray
    z: np.ndarray
    nominal: np.ndarray
    incidence: np.ndarray
    seg_start: np.ndarray
    seg_range: np.ndarray
    seg_hits: np.ndarray
    seg_passes: np.ndarray
    seg_occupied: np.ndarray
    seg_incidence: np.ndarray
    seg_line_incidence: np.ndarray
    seg_surface: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.z)

    @property
    def n(self) -> int:
        return int(self.z.size)

    @property
    def seg_at(self) -> np.ndarray:
        """(E,) range (m) of each segment's surface (:meth:`CellLines.surface_range`) where known, else its entry."""
        return np.where(np.isfinite(self.seg_surface), self.seg_surface, self.seg_range)

    @property
    def seg_line_like(self) -> np.ndarray:
        """(E,) whether the protocol's rule finds a line in each segment's neighbourhood (its line incidence known)."""
        return np.isfinite(self.seg_line_incidence)

    @property
    def seg_beam(self) -> np.ndarray:
        """(E,) the beam of each segment."""
        return np.repeat(np.arange(self.n), np.diff(self.seg_start))

    def first_occupied(self) -> np.ndarray:
        """(B,) index (into the segments) of each beam's first ``occ3`` occupied segment (-1: none)."""
        occupied = np.flatnonzero(self.seg_occupied == 1)
        beams, first = np.unique(self.seg_beam[occupied], return_index=True)
        out = np.full(self.n, -1)
        out[beams] = occupied[first]
        return out

    @classmethod
    def concatenate(cls, parts: list[PlanarTrace]) -> PlanarTrace:
        """One trace of several (beams in order)."""
        offsets = np.cumsum([0] + [p.seg_range.size for p in parts])
        start = np.concatenate([p.seg_start[:-1] + o for p, o in zip(parts, offsets)] + [[offsets[-1]]])
        fields = ("scan", "beam", "z", "nominal", "incidence") + SEGMENT_FIELDS
        values = {f: np.concatenate([getattr(p, f) for p in parts]) for f in fields}
        return cls(seg_start=start, **values)

    def take(self, which: np.ndarray) -> PlanarTrace:
        """The beams ``which`` (a bool mask, or indices in any order, repeats allowed), with their segments."""
        index = np.flatnonzero(which) if np.asarray(which).dtype == bool else np.asarray(which, np.int64)
        counts, rows = self.segment_rows(index)
        start = np.concatenate([[0], np.cumsum(counts)])
        return PlanarTrace(
            scan=self.scan[index],
            beam=self.beam[index],
            z=self.z[index],
            nominal=self.nominal[index],
            incidence=self.incidence[index],
            seg_start=start,
            **{f: getattr(self, f)[rows] for f in SEGMENT_FIELDS},
        )

    def segment_rows(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(counts, rows)``: the number of segments of each beam ``index`` (indices), and the rows of all
        their segments, beam after beam."""
        counts = np.diff(self.seg_start)[index]
        start = np.cumsum(counts) - counts
        return counts, np.repeat(self.seg_start[index] - start, counts) + np.arange(int(counts.sum()))

    def with_backstops(self, depth: float = BACKSTOP_DEPTH) -> PlanarTrace:
        """This trace with one more segment, a *backstop*, ``depth`` m behind the last segment of every beam
        that has one (``seg_occupied`` :data:`BACKSTOP`, no hits or passes, the last segment's incidence).

        A beam that passes every cell listed for it has not left the building: the list stops
        ``beyond`` m past its nominal hit, and a cell the leave-out map lacks (a wall seen only by the
        scans left out, one 5 cm cell of a wall grazed) lets a beam through that the wall stopped. Sent
        on to the escape state (the law of beams that met no cell at all), such beams were predicted to
        miss 30 % of the time on FHW (that state's P(null)), and so the beams whose first occupied cell
        was nearer than 8 m 0.5-1.2 % of the time, where the sensor missed none. The backstop is what
        such a beam meets next: an element with its own interception probability (fitted like the
        cells' Beta priors) and its own return law, shrunk to that of an occupied cell the map has not seen
        (:func:`~mi_lidar.planar.beams.segment_labels`, :func:`~mi_lidar.planar.permeable.backstop_prior`).

        A beam *in the open* (no ``occ3`` cell listed, only stray hits: people, foliage, far clutter) is
        another population: it mostly misses, or returns far off. Its backstop (:data:`OPEN_BACKSTOP`) and its
        stray cells (:data:`OPEN_STRAY`) get classes of their own. Sharing the stray cells' and the backstop's
        laws with the beams that met a wall, the Freiburg campus's beams that passed a wall 5-10 m away were
        predicted to miss 7.1 % of the time where 3.4 % of the training beams did, and its beams in the open
        made 11.3 % of the sampled test returns where they made 8.6 % of the measured ones.
        """
        counts = np.diff(self.seg_start)
        has = counts > 0
        walled = self.first_occupied() >= 0
        start = np.concatenate([[0], np.cumsum(counts + has)])
        moved = np.arange(self.seg_range.size) + np.repeat(start[:-1] - self.seg_start[:-1], counts)
        last, at = self.seg_start[1:][has] - 1, start[1:][has] - 1
        behind = {
            "seg_range": self.seg_at[last] + depth,
            "seg_hits": 0,
            "seg_passes": 0,
            "seg_occupied": np.where(walled[has], BACKSTOP, OPEN_BACKSTOP),
            "seg_incidence": self.seg_incidence[last],
            "seg_line_incidence": self.seg_line_incidence[last],
            "seg_surface": np.nan,
        }
        fields = {}
        for f in SEGMENT_FIELDS:
            values = getattr(self, f)
            out = np.empty(start[-1], np.int64 if f == "seg_occupied" else values.dtype)  # bool until now
            out[moved], out[at] = values, behind[f]
            fields[f] = out
        fields["seg_occupied"][moved] = np.where(walled[self.seg_beam], self.seg_occupied, OPEN_STRAY)
        return dataclasses.replace(self, seg_start=start, **fields)

    def neighbour(self, k: int) -> np.ndarray:
        """(B,) index of beam ``i + k`` of the same scan for every beam ``i``; ``i`` itself past the scan's edge."""
        i = np.arange(self.n)
        j = np.clip(i + k, 0, max(self.n - 1, 0))
        return np.where(self.scan[j] == self.scan, j, i)

    def shifted(self, k: int) -> PlanarTrace:
        """Beam ``i + k`` of the same scan in place of every beam ``i``, with beam ``i``'s measurement.

        Past the scan's edge a beam keeps its own trace. These are the traced neighbours of a beam:
        where a beam turned by ``k`` beam spacings goes, seen from the same pose through the same
        leave-out map.
        """
        return dataclasses.replace(self.take(self.neighbour(k)), z=self.z, beam=self.beam, scan=self.scan)

    def footprint(self, k: int) -> PlanarTrace:
        """Every beam ``i`` with the segments of its own trace and of beam ``i + k``'s (:meth:`neighbour`) merged
        in range order, and its own measurement.

        Each segment still intercepts on its own, so the first return along the merged list is the
        nearer of the two directions' first returns: what a beam reports whose footprint covers both
        (a post in one direction stops it, whatever lies behind the post in the other). A cell that both
        directions cross is met twice, once by each. Past the scan's edge a beam keeps its own trace, not
        doubled.
        """
        other = self.neighbour(k)
        paired = np.flatnonzero(other != np.arange(self.n))  # beams with a neighbour in their scan
        counts = np.diff(self.seg_start)
        other_count, other_rows = self.segment_rows(other[paired])
        segment = np.concatenate([np.arange(self.seg_range.size), other_rows])
        beam_of = np.concatenate([self.seg_beam, np.repeat(paired, other_count)])
        segment = segment[np.lexsort((self.seg_at[segment], beam_of))]
        start = np.concatenate([[0], np.cumsum(counts + np.bincount(paired, other_count, self.n).astype(np.int64))])
        return dataclasses.replace(self, seg_start=start, **{f: getattr(self, f)[segment] for f in SEGMENT_FIELDS})

    def first_occupied_range(self) -> np.ndarray:
        """(B,) range (m) of each beam's first ``occ3`` occupied segment's surface (NaN: none)."""
        first = self.first_occupied()
        return np.where(first >= 0, self.seg_at[np.maximum(first, 0)], np.nan)
