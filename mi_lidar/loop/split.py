"""Training and held-out rays of a log: the split every fit of the loop is judged on.

Rays are split by whole scans (alternate scans), so that a held-out ray never shares a scan, and so
a pose, with a training ray; a log of one scan is split into alternate blocks of 64 columns (or 64
beams when the scan has more beams than columns, as a planar scan of N beams x 1 firing has).
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log


def split_rays(log: Log, max_train: int, max_test: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Training and held-out ray indices (into the log's flattened rays), each sorted.

    Each split is subsampled (without replacement, fixed ``seed``) to at most its maximum.

    Raises:
        LogFormatError: one scan too small to hold out a block (65 columns or beams at least).
    """
    s, h, w = log.shape
    scan, beam, column = np.meshgrid(np.arange(s), np.arange(h), np.arange(w), indexing="ij")
    train = (scan.ravel() % 2 == 0) if s > 1 else (((column if w >= h else beam).ravel() // 64) % 2 == 0)
    if train.all():
        raise LogFormatError(
            f"the log holds one scan of {h} beams x {w} firings: too few to hold out a block of 64 rays; "
            "give a log of two scans or more"
        )
    rng = np.random.default_rng(seed)

    def cap(index, size):
        return np.sort(rng.choice(index, size, replace=False)) if index.size > size else index

    return cap(np.flatnonzero(train), max_train), cap(np.flatnonzero(~train), max_test)


def subsample(index: np.ndarray, size: int, seed: int) -> np.ndarray:
    """At most ``size`` of ``index``, drawn without replacement with ``seed`` and sorted."""
    return np.sort(np.random.default_rng(seed).permutation(index)[:size])
