"""A reference for the sample metrics: the measured test scans, re-paired between beams of like nominal range.

One sampled scan against the measured one, beam by beam (median and p90 |error|, hit/miss F1), rewards
a model for drawing the sensor's short and long returns and its no-returns *at the same beams* as the
measurement. Most of them are not predictable beam by beam (a person walking by, a glass pane seen at
one angle), so a model that never draws them (M0) scores better there than the sensor itself would.
To show what a model that samples like the sensor scores, every test beam is given the measured
outcome of another test beam: one of another scan, of the same kind (nominal hit in the map, or nominal
miss), drawn among its :data:`NEIGHBOURS` nearest on either side in nominal range (nominal misses: in
beam index). The other beam's residual is moved to this beam's nominal range
(``z_i = r_i + (z_j - r_j)``, at least 0); a no-return stays a no-return.

This is the sensor's own law given the nominal range alone: coarser than what a model of the map can
condition on (cells, incidence, neighbouring beams), so a good model may beat it on the median error
and the CRPS. It reads the test scans, so it is a reference, not a model, and has no NLL.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.planar.trace import PlanarTrace

NEIGHBOURS = 20  # a beam's partner is drawn among this many beams on either side in nominal range
ATTEMPTS = 64  # draws of a partner (another scan, same kind) before a beam keeps its own outcome


def repaired_scans(trace: PlanarTrace, draws: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``draws`` re-pairings of the measured scans of ``trace`` (see the module docstring).

    A beam for which no partner is found in :data:`ATTEMPTS` draws (its kind holds one scan's beams
    only) keeps its own outcome.

    Args:
        trace: the test beams (measured range ``z``, NaN for a no-return; nominal range, NaN for a
            nominal miss; scan and beam indices).
        draws: number of re-paired scans.
        seed: seed of the partners' draws.

    Returns:
        (draws, B) ranges (m; NaN where no return) and (draws, B) return flags.
    """
    n = trace.n
    rng = np.random.default_rng(seed)
    nominal_hit = np.isfinite(trace.nominal)
    key = np.where(nominal_hit, trace.nominal, trace.beam.astype(np.float64))
    order = np.lexsort((rng.random(n), key, ~nominal_hit))  # kind, then nominal range, ties at random
    kind, scan = nominal_hit[order], trace.scan[order]
    ranges, hits = np.empty((draws, n)), np.empty((draws, n), bool)
    for d in range(draws):
        partner = np.arange(n)  # position in ``order`` of each position's partner
        todo = np.arange(n)
        for _ in range(ATTEMPTS):
            if not todo.size:
                break
            step = rng.integers(1, NEIGHBOURS + 1, todo.size) * rng.choice((-1, 1), todo.size)
            j = np.abs(todo + step)  # reflected at both ends
            j = np.clip(np.where(j >= n, 2 * (n - 1) - j, j), 0, n - 1)
            found = (kind[j] == kind[todo]) & (scan[j] != scan[todo])
            partner[todo[found]] = j[found]
            todo = todo[~found]
        source = order[partner]
        z = trace.z[source]
        shift = np.where(nominal_hit[order], trace.nominal[order] - trace.nominal[source], 0.0)
        ranges[d, order] = np.maximum(z + shift, 0.0)
        hits[d, order] = np.isfinite(z)
    return ranges, hits
