"""What the planar benchmark keeps in memory: no per-segment beams after scoring, and freed arrays handed back."""

import gc
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from mi_lidar.core.streams import BeamCorrelation
from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar.angular import AngularMixture
from mi_lidar.planar.benchmark import run_planar_benchmark, scan_parts, scores_in_parts
from mi_lidar.planar.mixture import StackedBeams
from mi_lidar.planar.permeable import fit_permeable_map
from mi_lidar.planar.protocol import PlanarProtocol, prepare
from tests.planar.world import room_log_text


def test_mi_lidar_row_keeps_no_beams_and_rebuilds_the_scored_ones(tmp_path):
    """mi-lidar's beams (every segment, three times for its angular spread) are built for scoring and dropped;
    ``row.engine`` builds them again, the very beams scored: their test log-likelihoods are the row's."""
    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=20))
    result = run_planar_benchmark(read_carmen(path), protocol=PlanarProtocol(window=5.0), models=("M0", "mi-lidar"))
    gc.collect()
    assert not [o for o in gc.get_objects() if isinstance(o, AngularMixture)]
    row = result.rows[-1]
    assert row.name == "mi-lidar"
    train, test, model = row.engine
    assert isinstance(test, StackedBeams) and test.n == result.data.test.n and train.n == result.data.train.n
    np.testing.assert_array_equal(test.log_likelihood(model), row.ll)
    np.testing.assert_array_equal(test.sample(model, 0)[1], row.sampled[1])


def test_scan_parts_hold_whole_scans_of_at_most_the_budget():
    scan = np.repeat([0, 1, 2, 3, 4], [3, 3, 5, 2, 2])
    parts = scan_parts(scan, 6)
    assert [p.tolist() for p in parts] == [[0, 1, 2, 3, 4, 5], [6, 7, 8, 9, 10], [11, 12, 13, 14]]
    assert [p.tolist() for p in scan_parts(scan, 2)][2] == [6, 7, 8, 9, 10]  # a longer scan is a part of its own
    assert scan_parts(scan[:0], 6) == []


def test_beams_scored_and_sampled_in_parts_give_what_the_whole_set_gives(tmp_path):
    """The test beams of a long log are scored and sampled a few scans at a time, in a part's memory; numbered as
    rays of one set, with the set's random streams, the parts give every figure of the whole set at once, also
    when neighbouring beams share their draws (the correlated streams run along each scan, across the parts):
    the same draws, and the same scores and P(miss) to float rounding (two P(miss) of 1e-16 once differed by
    7e-40, a float32 denormal, in the last place)."""
    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=20))
    data = prepare(read_carmen(path), PlanarProtocol(window=5.0), workers=1)
    fitted = fit_permeable_map(data.train, 50.0, (0.1, 10.0, 0.01, 1.0, 0.1), classes=1, rounds=1, tails=False)
    fitted.angular, fitted.correlation = 0.1, BeamCorrelation(shared=0.6, rho=0.9)
    whole = scores_in_parts(fitted.beams, data.test, fitted.model, draws=3, seed=5, part_beams=10**9)
    parts = scores_in_parts(fitted.beams, data.test, fitted.model, draws=3, seed=5, part_beams=200)
    assert len(scan_parts(data.test.scan, 200)) == 4  # four test scans of 181 beams, one per part
    for a, b in zip(whole[:2], parts[:2]):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-30)
    for a, b in zip(whole[2:], parts[2:]):
        np.testing.assert_array_equal(a, b)
    ranges, hits = whole[2:]
    both = hits[0] & hits[1]
    assert ranges.shape == (3, data.test.n) and np.any(ranges[0][both] != ranges[1][both])  # the draws differ


def test_map_large_blocks_hands_freed_arrays_back():
    """After :func:`map_large_blocks`, 2 MB arrays freed between small live ones leave the resident memory.

    Without it, glibc raises its threshold above the 4 MB block freed first, the 2 MB arrays come from the
    heap between the small ones, and none of their 300 MB goes back (measured: 0 MB; with it: 300 MB)."""
    script = textwrap.dedent(
        """
        import numpy as np
        from mi_lidar.core.resources import map_large_blocks

        def resident_mb():
            for line in open("/proc/self/status"):
                if line.startswith("VmRSS"):
                    return int(line.split()[1]) / 1024

        assert map_large_blocks()
        np.ones(2**19).sum()  # a 4 MB block, freed
        big, small = [], []
        for k in range(150):
            big.append(np.ones(2**18))  # 2 MB
            small.append(np.ones(2**10))  # 8 kB between them
        before = resident_mb()
        del big
        print(before - resident_mb())
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert float(out.stdout) > 250.0  # of the 300 MB freed


@pytest.mark.parametrize("verb", ["benchmark-planar", "evaluate-apps"])
def test_both_planar_log_verbs_hand_freed_arrays_back(tmp_path, monkeypatch, verb):
    """evaluate-apps runs the planar benchmark on the whole log too, then forks its workers, but did not call
    :func:`map_large_blocks`: on the Intel log (--runs 1 --draws 2) its peak RSS was 1.76 GB, 1.43 GB with it.
    Both verbs now set the threshold before they read the log (here a file they refuse)."""
    import mi_lidar.core.resources
    from mi_lidar.io.dispatch import write_any
    from tests.io.test_clouds import synthetic_log
    from tests.terminal import invoke_at_80

    calls = []
    monkeypatch.setattr(mi_lidar.core.resources, "map_large_blocks", lambda: calls.append(True) or True)
    path = write_any(synthetic_log(), tmp_path / "scan.ply")
    result = invoke_at_80([verb, path, "--out", tmp_path / "out"])
    assert result.exit_code == 2 and "expected a CARMEN log" in " ".join(result.output.split()), result.output
    assert calls == [True]


def test_the_map_is_counted_in_chunks_of_bounded_march_whatever_the_range(monkeypatch, tmp_path):
    """Counting marched 64 scans at a time: 4.8 GB at once for a 360-beam outdoor log returning up to 82 m
    (Freiburg campus; 1.6 GB since). The default chunk holds about ``SAMPLES_PER_CHUNK`` beam samples (here
    made small, so that the 20-scan room is counted in several chunks): every march stays within twice it,
    and the counts are those of one 64-scan chunk."""
    from mi_lidar.planar import grid as grid_module
    from mi_lidar.planar.grid import Grid, count_scans

    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=20))
    log = read_carmen(path)
    grid = Grid.around(log.poses[:, :2, 3], 0.05, margin=8.0)
    whole = count_scans(log, grid, chunk=64)
    monkeypatch.setattr(grid_module, "SAMPLES_PER_CHUNK", 100_000)
    marched = []
    march = grid_module.march_cells

    def recorded(grid, origin, direction, length, step):
        marched.append(int(np.sum(np.ceil(np.maximum(length, 0) / step))))
        return march(grid, origin, direction, length, step)

    monkeypatch.setattr(grid_module, "march_cells", recorded)
    chunked = count_scans(log, grid)
    assert len(marched) > 3 and max(marched) < 2 * 100_000, marched
    for name in ("hit_start", "hit_cell", "hit_xy", "pass_start", "pass_cell"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)


def test_cell_lines_are_fitted_in_chunks_of_pairs_with_the_same_result(monkeypatch, tmp_path):
    """The local line fits of a batch's cells took some 30 arrays of 29 x 2 floats per distinct (scan, cell)
    pair at once (0.85 GB for 96 scans of the Freiburg campus log); fitted in chunks of pairs (here 7,
    so that the room's pairs make many chunks), every fit is the same as in one piece."""
    from mi_lidar.planar import raymarch
    from mi_lidar.planar.grid import CountMap, Grid, count_scans

    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=20))
    log = read_carmen(path)
    grid = Grid.around(log.poses[:, :2, 3], 0.05, margin=8.0)
    protocol = PlanarProtocol(window=5.0)
    leave = CountMap(count_scans(log, grid)).leave_out([protocol.excluded(log, q) for q in (3, 11)])
    query = np.repeat([0, 1], 400)
    cell = np.concatenate([np.unique(count_scans(log, grid).hit_cell)[:400]] * 2)
    whole = raymarch.CellLines.fit(leave, grid, query, cell)
    monkeypatch.setattr(raymarch, "FIT_PAIRS", 7)
    chunked = raymarch.CellLines.fit(leave, grid, query, cell)
    for name in ("at", "normal", "line_like", "centre", "surface_normal", "surface_line", "oriented", "own"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)
    assert whole.line_like.any() and whole.surface_line.any() and whole.oriented.any()
