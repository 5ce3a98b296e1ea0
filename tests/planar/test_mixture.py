"""Mixtures of planar beams: the shares' fit, and mi-lidar's stacked maps (mi_lidar.planar.mixture)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mi_lidar.core.likelihood import FLOOR, RESOLUTION
from mi_lidar.core.streams import uniform
from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar.mixture import STACK_STREAM, fit_shares
from mi_lidar.planar.permeable import StackedMaps, fit_permeable_map
from mi_lidar.planar.protocol import PlanarProtocol, prepare
from tests.planar.world import room_log_text


def test_the_stacked_shares_maximise_the_one_score():
    """Two parts, no groups: the EM's shares match the best of a 0.001 grid on the same score (random parts)."""
    rng = np.random.default_rng(7)
    n = 4000
    hit = rng.random(n) < 0.9
    p = rng.gamma(0.5, 1.0, (2, n)) * np.array([[1.0], [0.6]])
    raw = np.log(p) - np.where(hit, math.log(RESOLUTION), 0.0)  # densities of 1 cm bins of probability p

    def score(w: float) -> float:
        return float(np.mean(np.log(w * p[0] + (1 - w) * p[1] + FLOOR)))

    shares = fit_shares(raw, hit, (0, 1), np.array([0.5, 0.5]))
    best = max(np.arange(0.0, 1.0005, 0.001), key=score)
    assert shares.sum() == pytest.approx(1.0)
    assert score(shares[0]) >= score(best) - 1e-7
    assert shares[0] == pytest.approx(best, abs=0.003) and 0.05 < best < 0.95  # a real mixture, not an end
    start = np.array([0.5, 0.5])
    np.testing.assert_array_equal(fit_shares(np.zeros((2, 10)), np.ones(10, bool), (0, 1), start), start)


@pytest.fixture(scope="module")
def two_maps(tmp_path_factory):
    path = tmp_path_factory.mktemp("room") / "room.log"
    path.write_text(room_log_text(scans=20))
    data = prepare(read_carmen(path), PlanarProtocol(window=5.0), workers=1)
    bandwidths = (0.1, 10.0, 0.01, 1.0, 0.1)
    one = fit_permeable_map(data.train, 50.0, bandwidths, classes=1, rounds=1, tails=False)
    five = fit_permeable_map(data.train, 50.0, bandwidths, classes=5, rounds=1, tails=False, lines=True)
    return data, one, five


def test_stacked_maps_score_the_mixture_of_the_maps_and_sample_each_beam_from_the_map_it_picks(two_maps):
    """Each map scores and samples the beams by its own model; stacked with shares 0.3 and 0.7 the raw likelihood
    is the mixture of theirs, P(miss) the mixture of theirs, and a sampled beam is what the map it picked (stream
    STACK_STREAM) draws alone with the same seed: 30 % of the beams within 4 binomial standard errors."""
    data, one, five = two_maps
    stack = StackedMaps(maps=(one, five), shares=np.array([0.3, 0.7]))
    beams, alone = stack.beams(data.test), [m.beams(data.test) for m in (one, five)]
    raw = [b.raw_log_likelihood(m.model) for b, m in zip(alone, (one, five))]
    mixed = np.logaddexp(math.log(0.3) + raw[0], math.log(0.7) + raw[1])
    np.testing.assert_allclose(beams.raw_log_likelihood(stack.model), mixed, rtol=1e-6)
    p_miss = 0.3 * alone[0].p_miss(one.model) + 0.7 * alone[1].p_miss(five.model)
    np.testing.assert_allclose(beams.p_miss(stack.model), p_miss, rtol=1e-6, atol=1e-12)

    z, hit = beams.sample(stack.model, 3)
    draws = [b.sample(m.model, 3) for b, m in zip(alone, (one, five))]
    picked_one = np.asarray(uniform(3, beams.ray_id, 0, STACK_STREAM), np.float64) < 0.3
    for picked, (z_k, hit_k) in ((picked_one, draws[0]), (~picked_one, draws[1])):
        np.testing.assert_array_equal(z[picked], z_k[picked])
        np.testing.assert_array_equal(hit[picked], hit_k[picked])
    assert np.any(draws[0][0] != draws[1][0])  # the maps draw differently: the test tells them apart
    se = math.sqrt(0.3 * 0.7 / beams.n)
    assert abs(picked_one.mean() - 0.3) < 4 * se


def test_a_stacked_model_takes_one_model_per_map(two_maps):
    data, one, five = two_maps
    beams = StackedMaps(maps=(one, five), shares=np.array([0.5, 0.5])).beams(data.test)
    with pytest.raises(ValueError, match="2 stacked maps need as many models; got 1"):
        beams.log_likelihood((one.model,))


def test_the_runner_up_is_stacked_only_where_the_mixture_gains_enough():
    """stack_choice keeps the best held-out candidate, and its runner-up only where mixed they gain at least
    MIN_STACK_GAIN nats per held-out beam: two candidates that each explain half the beams well are stacked near
    half and half; a runner-up that is the best with a little noise is not."""
    from mi_lidar.planar.permeable import MIN_STACK_GAIN, stack_choice

    rng = np.random.default_rng(3)
    n = 6000
    hit = np.ones(n, bool)
    good, poor = math.log(20.0), math.log(2.0)  # densities (1/m): 20 % and 2 % of a 1 cm bin
    half = rng.random(n) < 0.5
    complementary = np.stack([np.where(half, good, poor), np.where(half, poor, good), np.full(n, poor)])
    kept, shares, scores, stacked = stack_choice(complementary, hit)
    assert sorted(kept.tolist()) == [0, 1] and shares == pytest.approx([0.5, 0.5], abs=0.03)
    assert stacked < min(scores) - MIN_STACK_GAIN
    alike = np.stack([np.full(n, good), np.full(n, good) + rng.normal(0.0, 0.01, n), np.full(n, poor)])
    kept, shares, scores, stacked = stack_choice(alike, hit)
    assert kept.tolist() == [int(np.argmin(scores[:2]))] and shares.tolist() == [1.0]
    assert min(scores) - MIN_STACK_GAIN <= stacked <= min(scores) + 1e-5  # float32 scores
