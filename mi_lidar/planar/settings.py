"""The real-planar protocol's settings (``docs/benchmark_planar.md``): the split, the leave-out neighbourhoods,
the map and the score. Kept apart from :mod:`mi_lidar.planar.protocol`, which uses them, so that the command line
reads its defaults from here without importing the map and the ray march."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.log import Log

MAX_TEST_EVERY = 10**9  # a test scan every 10**9 scans already tests scan 0 alone: more is a typo


@dataclass(frozen=True)
class PlanarProtocol:
    """Settings of the protocol (defaults: the protocol's).

    Attributes:
        cell: grid cell, m.
        test_every: every ``test_every``-th scan (0, k, 2k, ...) is a test scan.
        radius, window: a query's map leaves out the scans within ``radius`` m and ``window`` s.
        reach: march limit and endpoint-hit limit, m.
        resolution: range bin of the score, m.
        max_segments, beyond: segments kept per beam for pass-through models, and how far past the
            nominal hit (m) they are collected.
        batch: query scans traced at once (memory; one batch per worker thread).
        train_beams: at most this many training beams are traced and fitted: on a longer log, evenly
            spaced training scans (the protocol allows a fixed subset of training scans on a long log
            to keep fitting fast). The default, 150,000 beams, keeps every training scan of a
            1,000-scan log of 180 or 181 beams (Intel: 131,040) and of a 520-scan log of 361 beams, and
            fits a 910-scan log of 361 beams (262,808) in the 5 minutes the benchmark is given on 2 cores
            (349 s with all of them at ``efdb56d``); 0: all.
    """

    cell: float = 0.05
    test_every: int = 5
    radius: float = 1.0
    window: float = 30.0
    reach: float = 40.0
    resolution: float = 0.01
    max_segments: int = 12
    beyond: float = 10.0
    batch: int = 96
    train_beams: int = 150_000

    def __post_init__(self):
        if not 3 <= self.test_every <= MAX_TEST_EVERY:  # (2**64 overflowed numpy's modulo: a traceback)
            raise ParameterError(
                f"test_every={self.test_every} must be from 3 (training scans are the others, and the learned models "
                "choose their settings on the even ones and check them on the odd ones: with 2 every training scan is "
                f"odd) to {MAX_TEST_EVERY:,} (no log has more scans)"
            )
        if self.train_beams < 0:
            raise ParameterError(f"train_beams={self.train_beams} must be >= 0 (0: every training scan)")
        if not 0.005 <= self.cell <= 1.0:
            raise ParameterError(f"cell={self.cell} m must lie in [0.005, 1], e.g. 0.05")

    def split(self, n_scans: int, beams_per_scan: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(test scans, training scans): the training scans evenly thinned to at most ``train_beams`` beams.

        The fits choose their settings on the even training scans and check them on the odd ones, so
        the kept scans alternate in parity: each evenly spaced pick of the wrong parity moves to its
        neighbouring training scan.
        """
        scans = np.arange(n_scans)
        test, train = scans[scans % self.test_every == 0], scans[scans % self.test_every != 0]
        most = max(2, self.train_beams // max(beams_per_scan, 1))
        if not self.train_beams or train.size <= most:
            return test, train
        picks = train[np.round(np.linspace(0, train.size - 1, most)).astype(np.int64)]
        wrong = picks % 2 != np.arange(most) % 2
        after, before = picks + 1, picks - 1
        is_train = np.isin(after, train)
        picks = np.where(wrong, np.where(is_train, after, before), picks)
        return test, np.unique(picks[np.isin(picks, train)])

    def excluded(self, log: Log, scan: int) -> np.ndarray:
        """The scans the map of ``scan`` leaves out (within ``radius`` m and ``window`` s; itself included)."""
        xy = log.poses[:, :2, 3]
        t = log.times[:, 0, 0]
        near = np.hypot(*(xy - xy[scan]).T) <= self.radius
        recent = np.abs(t - t[scan]) <= self.window
        out = np.flatnonzero(near & recent)
        return out if scan in out else np.union1d(out, [scan])
