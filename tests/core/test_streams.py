"""Random streams correlated between neighbouring beams: exact marginals, the stated joint law, restarts per scan."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy import stats
from scipy.special import ndtri

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.streams import BeamCorrelation, NeighbourStreams, ar1, scan_follows, uniform

SCANS, BEAMS = 400, 180


def _streams(correlation: BeamCorrelation, seed: int = 3) -> NeighbourStreams:
    scan, beam = np.divmod(np.arange(SCANS * BEAMS), BEAMS)
    return NeighbourStreams(seed=seed, follows=scan_follows(scan, beam), correlation=correlation)


def _draw(streams: NeighbourStreams, segment: int = 0, stream: int = 1) -> np.ndarray:
    return np.asarray(streams.uniform(dr.arange(mi.UInt32, SCANS * BEAMS), segment, stream), np.float64)


def _lag(scores: np.ndarray, k: int) -> float:
    """Correlation of scores ``k`` beams apart within a scan."""
    s = scores.reshape(SCANS, BEAMS)
    return float(np.corrcoef(s[:, :-k].ravel(), s[:, k:].ravel())[0, 1])


def test_no_correlation_gives_the_counter_based_outcome_numbers():
    streams = _streams(BeamCorrelation())
    ids = dr.arange(mi.UInt32, SCANS * BEAMS)
    assert np.array_equal(_draw(streams, 2, 0), np.asarray(uniform(3, ids, 2, 0)))


def test_range_draws_are_shared_by_the_segments_of_a_ray_and_outcomes_are_not():
    streams = _streams(BeamCorrelation(shared=0.5, rho=0.5))
    assert np.array_equal(_draw(streams, 0, 1), _draw(streams, 3, 1))
    assert abs(np.corrcoef(_draw(streams, 0, 0), _draw(streams, 3, 0))[0, 1]) < 0.02


def test_correlated_numbers_are_uniform_with_the_stated_lag_correlations():
    # Beams 45 apart share 0.6 * 0.9^45 < 0.01 of their score: 1,600 nearly independent draws, whose KS
    # statistic stays below 0.05 with probability 0.999 when they are uniform. The lag correlations'
    # standard error over 72,000 draws is about 0.004 (0.02 = 5 SE).
    correlation = BeamCorrelation(shared=0.6, rho=0.9)
    u = _draw(_streams(correlation))
    assert u.min() >= 0.0 and u.max() < 1.0
    assert stats.kstest(u.reshape(SCANS, BEAMS)[:, ::45].ravel(), "uniform").statistic < 0.05
    scores = ndtri(u)
    for k in (1, 2, 5, 10):
        assert _lag(scores, k) == pytest.approx(correlation.lag(k), abs=0.02)


def test_streams_and_segments_are_independent_of_each_other():
    streams = _streams(BeamCorrelation(shared=0.8, rho=0.95))
    a, b, c = ndtri(_draw(streams, 0, 0)), ndtri(_draw(streams, 0, 1)), ndtri(_draw(streams, 1, 0))
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.02
    assert abs(np.corrcoef(a, c)[0, 1]) < 0.02


def test_scans_do_not_share_their_draws():
    scores = ndtri(_draw(_streams(BeamCorrelation(shared=0.9, rho=0.99)))).reshape(SCANS, BEAMS)
    # last beam of a scan against the first of the next: independent (SE 0.05 over 399 pairs)
    assert abs(np.corrcoef(scores[:-1, -1], scores[1:, 0])[0, 1]) < 0.2
    assert np.corrcoef(scores[:, 0], scores[:, 1])[0, 1] > 0.8


def test_ar1_is_stationary_from_the_first_beam():
    drive = np.random.default_rng(0).standard_normal((20000, 4))
    follows = np.tile([False, True, True, True], 20000)
    a = ar1(drive.ravel(), follows, 0.7).reshape(20000, 4)
    assert np.std(a, axis=0) == pytest.approx(np.ones(4), abs=0.02)
    assert np.corrcoef(a[:, 0], a[:, 3])[0, 1] == pytest.approx(0.7**3, abs=0.03)


def test_scan_follows_marks_consecutive_beams_of_one_scan():
    follows = scan_follows(np.array([0, 0, 0, 1, 1, 1]), np.array([0, 1, 3, 0, 1, 2]))
    assert follows.tolist() == [False, True, False, False, True, True]


@pytest.mark.parametrize("shared, rho", [(1.0, 0.5), (-0.1, 0.5), (0.5, 1.0), (0.5, float("nan"))])
def test_correlation_out_of_range_is_refused_with_its_name(shared, rho):
    with pytest.raises(ParameterError, match="shared|rho"):
        BeamCorrelation(shared=shared, rho=rho)


def test_a_symbolic_segment_counter_is_refused():
    with pytest.raises(TypeError, match="Python int"):
        _streams(BeamCorrelation(0.5, 0.5)).uniform(dr.arange(mi.UInt32, 4), mi.UInt32(0), 0)


def _pass_through(p: list[float], rays: int):
    """``rays`` rays through the same elements of interception ``p`` at 10, 20, 30 ... m (1 cm noise)."""
    from mi_lidar.core.elements import ElementTable
    from mi_lidar.core.rays import RayBatch
    from mi_lidar.core.trace import rounds_from_segments

    k = len(p)
    table = ElementTable.from_elements(np.array(p), range_sigma=np.full(k, 0.01))
    start = np.arange(rays + 1) * k
    rounds = rounds_from_segments(
        start, np.tile(np.arange(k), rays), np.tile(10.0 * np.arange(1, k + 1), rays), np.ones(rays * k)
    )
    batch = RayBatch(
        origin=mi.Point3f(0.0),
        direction=mi.Vector3f(1.0, 0.0, 0.0),
        beam=dr.arange(mi.UInt32, rays) % BEAMS,
        time=dr.zeros(mi.Float, rays),
        ray_id=dr.arange(mi.UInt32, rays),
    )
    return table, batch, rounds


def test_carried_outcomes_keep_the_pass_through_law():
    """P(return from element k) = p_k prod_(j<k) (1 - p_j): with p = 0.5, 0.4, 0.9 that is 0.5, 0.2,
    0.27 and a miss 0.03. 72,000 correlated rays (shared 0.8, rho 0.9) carry about 72,000 / 19 ~ 3,800
    independent ones (an AR(1) block of 1 + 2 * rho / (1 - rho) beams): a share's SE is below 0.009;
    tolerance 0.035 (4 SE)."""
    from mi_lidar.core.sensor_model import SensorModel

    table, rays, rounds = _pass_through([0.5, 0.4, 0.9], SCANS * BEAMS)
    streams = _streams(BeamCorrelation(shared=0.8, rho=0.9))
    z, hit = SensorModel(max_range=100.0).sample_trace(table, rays, rounds, streams)
    z, hit = np.asarray(z), np.asarray(hit)
    shares = [np.mean(hit & (np.abs(z - r) < 1.0)) for r in (10.0, 20.0, 30.0)] + [np.mean(~hit)]
    assert shares == pytest.approx([0.5, 0.2, 0.27, 0.03], abs=0.035)
    # neighbours stop at the same element far more often than independent beams would
    stop = np.where(hit, np.round(np.nan_to_num(z) / 10.0), 0).reshape(SCANS, BEAMS)
    same = np.mean(stop[:, 1:] == stop[:, :-1])
    assert same > 0.5**2 + 0.2**2 + 0.27**2 + 0.03**2 + 0.2


@pytest.mark.parametrize("seed", [2**32, 2**64, -1])
def test_a_seed_beyond_32_bits_is_refused_before_it_repeats_another(seed):
    """simulate(seed=2**32) gave the very scan of seed 0 (labelled 2**32); seed -1 that of 2**32 - 1."""
    import mi_lidar
    from tests.conftest import SCENES

    scene = mi_lidar.load_scene(SCENES / "indoor_planar.xml")
    with pytest.raises(ParameterError, match=rf"seed {seed} is outside 0 \.\. 4294967295: .* repeat the draws of seed"):
        mi_lidar.simulate(scene, seed=seed)
    with pytest.raises(ParameterError, match=rf"seed {seed} is outside"):
        _streams(BeamCorrelation(), seed=seed)
    assert mi_lidar.simulate(scene, seed=2**32 - 1).n_scans == 1
