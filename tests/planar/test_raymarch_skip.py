"""The ray march skips the samples far from any hit and still records what the plain march records, to the bit.

The reference is the protocol's march written out per ray, sample by sample, at the distances the
march accumulates (``t += step``): every sample's cell, the side cells of every corner it crosses,
the leave-out counts of each. The world is a courtyard: a few walls, a pillar, a fence that returns
a third of the beams (cells with hits that are not occupied), and open space all around, so most
beams run far through empty cells (out of the map's grid, or to the 40 m reach on a grid with room).
"""

from __future__ import annotations

import numpy as np
import pytest

from mi_lidar.io.carmen import beam_angles, read_carmen
from mi_lidar.planar.grid import CountMap, Grid, count_scans, planar_beams
from mi_lidar.planar.protocol import PlanarProtocol
from mi_lidar.planar.raymarch import START, CellLines, entry_distance, trace_scans
from tests.planar.world import cast, pillar

WALLS = np.concatenate(
    [np.array([[0, 0, 10, 0], [0, 0, 0, 6], [12, 2, 16, 8]], float), pillar(5.5, 5.5)]  # diagonal: corner crossings
)
FENCE = np.array([[2.0, 9.0, 9.0, 9.0]])
PROTOCOL = PlanarProtocol(window=5.0)
QUERIES = [3, 17, 30]


@pytest.fixture(scope="module")
def courtyard(tmp_path_factory):
    """A CARMEN log of 40 scans of 91 beams, driving two loops in the courtyard (first pose: heading exactly 0)."""
    rng = np.random.default_rng(7)
    a = np.linspace(0, 4 * np.pi, 40, endpoint=False)
    poses = np.stack([6 + 3.0 * np.cos(a), 3 + 1.5 * np.sin(a), a], axis=1)
    poses[20, 2] = np.pi / 2  # a beam along y
    lines = []
    for s, (x, y, heading) in enumerate(poses):
        angle = heading + beam_angles(91)
        direction = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        origin = np.repeat([[x, y]], 91, axis=0)
        wall = cast(origin, direction, WALLS).min(axis=1)
        fence = cast(origin, direction, FENCE)[:, 0]
        z = np.where((fence < wall) & (rng.random(91) < 0.3), fence, wall) + rng.normal(0.0, 0.02, 91)
        z = np.where(np.isfinite(z) & (z < 50.0), z, 50.0)
        t = 100.0 + 0.2 * s
        pose = f"{x:.4f} {y:.4f} {heading:.5f}"
        lines.append(f"FLASER 91 {' '.join(f'{r:.3f}' for r in z)} {pose} {pose} {t:.3f} host {t:.3f}")
    path = tmp_path_factory.mktemp("courtyard") / "courtyard.log"
    path.write_text("\n".join(lines) + "\n")
    return read_carmen(path, max_range=50.0)


def reference_march(grid, o, d, hits, occ, reach, max_segments, beyond):
    """One ray's march, sample by sample: (nominal cell or -1, segment cells, samples walked, how it ended).

    The end is "grid" (left it), "full" (segment list), "stop" (``beyond`` past the nominal hit), "reach",
    and "corner" is added when the nominal hit is a side cell closing a corner.
    """
    step = grid.cell / 4
    ts, t = [], START
    while t <= reach:
        ts.append(t)
        t += step
    cells = grid.ij(o + np.array(ts)[:, None] * d).tolist()
    nx, ny = grid.shape

    def flat(c):
        return c[0] * ny + c[1] if 0 <= c[0] < nx and 0 <= c[1] < ny else -1

    prev, look, stop, first, segments, end, corner = cells[0], True, reach, -1, [], {"reach"}, set()
    for k in range(len(ts)):
        t, cell = ts[k], cells[k]
        if cell != prev or look:  # a new cell (or the first, or the cell after a closed corner)
            here = flat(cell)
            if here < 0:
                end = {"grid"}
                break
            closed = -1
            if cell[0] != prev[0] and cell[1] != prev[1]:  # a corner: closed by an occupied side cell
                for side in ((cell[0], prev[1]), (prev[0], cell[1])):
                    if flat(side) >= 0 and occ[flat(side)]:
                        closed = flat(side)
                        break
            segment = closed if closed >= 0 else (here if hits[here] >= 1 else -1)
            hit = closed if closed >= 0 else (here if occ[here] else -1)
            nominal = hit >= 0 and first < 0
            if segment >= 0 and (not segments or segments[-1] != segment):
                if len(segments) < max_segments:
                    segments.append(segment)
                elif nominal:  # a full list still takes the nominal hit, in its last slot
                    segments[-1] = segment
            if nominal:
                first, stop, end = hit, min(reach, t + beyond), {"stop"}
                corner = {"corner"} if closed >= 0 else set()
            prev, look = cell, closed >= 0
            if len(segments) >= max_segments and first >= 0:
                end = {"full"}
                break
        if t + step > stop:
            break
    return first, segments, k + 1, end | corner


@pytest.mark.parametrize("margin, max_segments, beyond", [(1.0, 4, 3.0), (45.0, 12, 10.0)])
def test_skipping_march_records_what_the_plain_march_records(courtyard, monkeypatch, margin, max_segments, beyond):
    log = courtyard
    origin, direction, z = planar_beams(log)
    ends = (origin + np.nan_to_num(z)[..., None] * direction)[np.isfinite(z)]
    # margin 1 m: open beams leave the grid; 45 m: they stop at the 40 m reach inside it
    grid = Grid.around(np.concatenate([ends, log.poses[:, :2, 3]]), 0.05, margin=margin)
    cmap = CountMap(count_scans(log, grid))
    scans = np.array(QUERIES)
    excluded = [PROTOCOL.excluded(log, q) for q in QUERIES]
    points = []
    real_ij = Grid.ij
    monkeypatch.setattr(Grid, "ij", lambda self, xy: points.append(xy.size // 2) or real_ij(self, xy))
    trace = trace_scans(log, grid, cmap, scans, excluded, PROTOCOL.reach, max_segments, beyond)
    monkeypatch.undo()

    leave = cmap.leave_out(excluded)
    o, d = origin[scans].reshape(-1, 2), direction[scans].reshape(-1, 2)
    query = np.repeat(np.arange(len(QUERIES)), log.shape[1])
    first, segments, walked, endings = [], [], 0, []
    for q in range(len(QUERIES)):
        h, n = leave.counts(np.full(grid.size, q), np.arange(grid.size))
        occ = (h >= 1) & (3 * h >= n)  # occ3
        for beam in np.flatnonzero(query == q):
            cell, cells, samples, end = reference_march(
                grid, o[beam], d[beam], h, occ, PROTOCOL.reach, max_segments, beyond
            )
            first.append(cell)
            segments.append(cells)
            walked += samples
            endings.append(end)
    first = np.array(first)
    has = first >= 0
    count = np.array([len(s) for s in segments])
    cells = np.array([c for s in segments for c in s], np.int64)
    rows = np.repeat(np.arange(first.size), count)
    hits, passes = leave.counts(query[rows], cells)
    lines = CellLines.fit(leave, grid, query[rows], cells)
    seg_inc = lines.incidence(d[rows])
    start = np.concatenate([[0], np.cumsum(count)])
    at_first = [start[b] + segments[b].index(first[b]) for b in np.flatnonzero(has)]
    incidence = np.full(first.size, np.nan)
    incidence[has] = seg_inc[at_first]

    nominal = np.full(first.size, np.nan)
    nominal[has] = entry_distance(grid, o[has], d[has], first[has])
    np.testing.assert_array_equal(trace.nominal, nominal)  # NaNs equal
    np.testing.assert_array_equal(trace.incidence, incidence)
    np.testing.assert_array_equal(trace.seg_start, start)
    np.testing.assert_array_equal(trace.seg_range, entry_distance(grid, o[rows], d[rows], cells))
    np.testing.assert_array_equal(trace.seg_hits, hits)
    np.testing.assert_array_equal(trace.seg_passes, passes)
    np.testing.assert_array_equal(trace.seg_incidence, lines.surface_incidence(d[rows]))
    # The reference met every way a march ends, and beams with and without a nominal hit.
    expected = {"grid", "stop", "corner", "full"} if margin < 10 else {"reach", "stop", "corner"}
    assert expected <= set().union(*endings), set().union(*endings)
    assert 0 < has.sum() < has.size and np.isfinite(incidence).any()
    # The skipping march placed a fraction of the samples the plain march walks.
    assert sum(points) < walked / 3, (sum(points), walked)
