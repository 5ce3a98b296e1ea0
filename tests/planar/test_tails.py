"""mi-lidar's permeable map after the hard EM: the tables' far tails scaled by likelihood (tails.fit_tails), their
no-return probabilities matched to the training beams (tails.match_misses)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mi_lidar.io.carmen import read_carmen
from mi_lidar.planar import tails
from mi_lidar.planar.beams import base_model
from mi_lidar.planar.permeable import fit_permeable_map
from mi_lidar.planar.protocol import PlanarProtocol, prepare
from mi_lidar.planar.tails import (
    FAR,
    SHORT_DRAWS,
    fit_tails,
    match_misses,
    match_short_returns,
    short_share,
    training_nll,
    with_tails,
)
from tests.planar.world import room_log_text


@pytest.fixture(scope="module")
def room_map(tmp_path_factory):
    """The simulated room's training beams and a permeable map fitted on them without the tails' fit."""
    path = tmp_path_factory.mktemp("tails") / "room.log"
    path.write_text(room_log_text(scans=40))
    data = prepare(read_carmen(path), PlanarProtocol(window=5.0))
    z_max = float(np.nanmax(data.log.ranges)) + 1.0
    return data, fit_permeable_map(data.train, z_max, (1.0, 0.2, 0.01, math.inf, 1.0), 1, rounds=1, tails=False)


def shares(density) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(states,) share of every state's table short of, near, and long of the surface (0 for an empty table)."""
    centres = 0.5 * (density.edges[1:] + density.edges[:-1])
    mass = density.mass / np.maximum(density.mass.sum(axis=1, keepdims=True), 1e-300)
    return tuple(mass[:, part].sum(axis=1) for part in (centres < -FAR, np.abs(centres) <= FAR, centres > FAR))


def test_scaling_the_tails_moves_only_their_mass(room_map):
    _, fitted = room_map
    density = fitted.model.density
    same = with_tails(density, 1.0, 1.0)
    np.testing.assert_array_equal(same.mass, density.mass)
    scaled = with_tails(density, 0.5, 2.0)
    (short, near, long), (short2, near2, long2) = shares(density), shares(scaled)
    used = near > 0.01
    short, near, long, short2, near2, long2 = (x[used] for x in (short, near, long, short2, near2, long2))
    total = 0.5 * short + near + 2.0 * long  # the renormalisation of each state
    np.testing.assert_allclose(near2, near / total, rtol=1e-9)
    np.testing.assert_allclose(short2, 0.5 * short / total, rtol=1e-9)
    np.testing.assert_allclose(long2, 2.0 * long / total, rtol=1e-9)
    np.testing.assert_array_equal(scaled.p_null, density.p_null)


def test_an_inflated_tail_is_pulled_back_and_the_score_improves(room_map):
    """Tables whose tails hold 16x the mass the EM gave them: the fit scales them back (to under half their
    share of the near mass; measured: short 0.05x, long 0.28x) and the training score improves (by 0.0117 nats
    per beam); the fitted tails' score is no worse than the EM's own. (8x was enough before the EM's last steps
    left out what the angular spread explains: from those thinner tables, 8x is pulled back to 0.56x only.)"""
    data, fitted = room_map
    beams = fitted.beams(data.train)

    def nll(density) -> float:
        return float(-np.mean(beams.log_likelihood(base_model(density))))

    inflated = with_tails(fitted.model.density, 16.0, 16.0)
    pulled = fit_tails(beams, inflated)
    (short, near, long), (short2, near2, long2) = shares(inflated), shares(pulled)
    used = (near > 0.01) & (short > 1e-6) & (long > 1e-6)
    assert used.sum() > 10
    assert np.all(short2[used] / near2[used] < 0.5 * short[used] / near[used])
    assert np.all(long2[used] / near2[used] < 0.5 * long[used] / near[used])
    assert nll(pulled) < nll(inflated) - 0.01, (nll(pulled), nll(inflated))
    assert nll(fit_tails(beams, fitted.model.density)) <= nll(fitted.model.density) + 1e-9


def test_no_returns_are_matched_to_the_training_beams(tmp_path):
    """A sensor that clips at 7 m in the room: tables whose no-return probabilities are tripled predict far
    more no-returns than the training beams have; matched, the mean P(miss) equals their rate (within 2e-4,
    float32 sums), the escape state (beams that met no cell) keeps its counted P(null), and the training score
    improves (measured by 0.16 nats per beam). Matching the tables
    as fitted brings their rate closer and moves the score less than MISS_TOLERANCE."""
    from mi_lidar.planar.tails import MISS_TOLERANCE

    path = tmp_path / "clipped.log"
    path.write_text(room_log_text(scans=30, max_range=7.0))
    data = prepare(read_carmen(path), PlanarProtocol(window=5.0))
    z_max = 7.0
    fitted = fit_permeable_map(data.train, z_max, (1.0, 0.2, 0.01, math.inf, 1.0), 1, rounds=1, tails=False)
    beams = fitted.beams(data.train)
    measured = float(np.mean(~data.train.hit))
    assert 0.02 < measured < 0.5

    def p_miss(density) -> float:
        return float(np.mean(beams.p_miss(base_model(density))))

    def nll(density) -> float:
        return float(-np.mean(beams.log_likelihood(base_model(density))))

    density = fitted.model.density
    tripled = density.with_tables(p_null=np.minimum(3.0 * density.p_null, 1.0))
    assert p_miss(tripled) > 1.2 * measured  # measured: 1.43
    first, one_band = data.train.first_occupied_range(), [0.0, 1.0e9]
    matched = match_misses(beams, tripled, first, one_band)
    assert p_miss(matched) == pytest.approx(measured, abs=2e-4)
    escaping = tripled.with_tables(p_null=np.concatenate([tripled.p_null[:-1], [0.6]]))
    assert match_misses(beams, escaping, first, one_band).p_null[-1] == 0.6  # the escape state keeps its P(null)
    assert nll(matched) < nll(tripled) - 0.003, (nll(matched), nll(tripled))
    again = match_misses(beams, density, first, one_band)
    assert abs(p_miss(again) - measured) <= abs(p_miss(density) - measured)  # closer (P(miss) capped at 1)
    assert nll(again) < nll(density) + MISS_TOLERANCE


def test_no_returns_are_matched_per_range_band(tmp_path, monkeypatch):
    """A sensor that misses more often the farther its first wall (P(miss) = 0.6 r / r_max, drawn with a
    fixed seed) and tables whose no-return probabilities are all 0.1: one common factor matches the overall
    rate but leaves the near band over and the far band under its rate by more than 0.05; matched per band
    (bands of at least 500 beams), every band's mean P(miss) is within 0.01 of its rate (float32 sums and
    the coupling left after MISS_ROUNDS rounds), and the training score improves on the common factor's."""
    monkeypatch.setattr(tails, "MISS_BAND_BEAMS", 500)
    path = tmp_path / "room.log"
    path.write_text(room_log_text(scans=30))
    data = prepare(read_carmen(path), PlanarProtocol(window=5.0))
    first = data.train.first_occupied_range()
    far = np.nanmax(first)
    drop = np.random.default_rng(7).random(first.size) < 0.6 * np.nan_to_num(first) / far
    train = dataclasses.replace(data.train, z=np.where(drop, np.nan, data.train.z))
    z_max = float(np.nanmax(data.log.ranges)) + 1.0
    fitted = fit_permeable_map(train, z_max, (1.0, 0.2, 0.01, math.inf, 1.0), 1, rounds=1, tails=False)
    beams = fitted.beams(train)
    density = fitted.model.density
    flat = density.with_tables(p_null=np.concatenate([np.full(density.grid.size, 0.1), [0.5]]))
    edges = [0.0, 1.5, 3.0, 4.5, 6.0, 1.0e9]
    bands = tails.miss_bands(first, edges)
    assert bands.size >= 4, bands  # at least three bands of >= 500 beams
    band = np.where(np.isfinite(first), np.clip(np.searchsorted(bands, first, side="right") - 1, 0, bands.size - 2), -1)

    def errors(density) -> np.ndarray:
        p = beams.p_miss(base_model(density))
        return np.array([p[band == b].mean() - np.mean(~train.hit[band == b]) for b in range(bands.size - 1)])

    def nll(density) -> float:
        return float(-np.mean(beams.log_likelihood(base_model(density))))

    common = match_misses(beams, flat, first, [0.0, 1.0e9])
    assert errors(common)[0] > 0.05 and errors(common)[-1] < -0.05, errors(common)
    banded = match_misses(beams, flat, first, edges)
    assert np.all(np.abs(errors(banded)) < 0.01), errors(banded)
    assert nll(banded) < nll(common) - 0.005, (nll(banded), nll(common))


def test_a_heavy_short_tail_is_matched_to_the_measured_short_returns(room_map):
    """Tables whose short tail holds 20x the EM's mass draw far more short returns (> FAR short of the nominal
    range) than the room's training beams hold; matched, the scans sampled with the fit's seeds hold the
    measured share within 0.004 (the bisection's resolution on 8 steps), and the training score is no
    worse than the inflated tables'. A tail that draws too few short returns (against the room's returns with
    4 % moved 2 m short) is left as it is."""
    data, fitted = room_map
    beams = fitted.beams(data.train)
    measured = short_share(data.train.z, data.train.hit, data.train.nominal)
    assert measured > 0.005

    def drawn(density) -> float:
        model = base_model(density)
        return float(
            np.mean([short_share(*beams.sample(model, seed), data.train.nominal) for seed in range(SHORT_DRAWS)])
        )

    heavy = with_tails(fitted.model.density, 20.0, 1.0)  # 2.29 % short returns drawn where 1.05 % were measured
    assert drawn(heavy) > measured + 0.01
    matched = match_short_returns(beams, data.train, heavy)
    assert abs(drawn(matched) - measured) < 0.004, (drawn(matched), measured)
    assert training_nll(beams, matched) <= training_nll(beams, heavy)
    light = with_tails(fitted.model.density, 0.05, 1.0)
    moved = data.train.hit & (np.arange(data.train.n) % 25 == 0)  # 4 % of the returns, 2 m short
    shorter = dataclasses.replace(data.train, z=np.where(moved, data.train.nominal - 2.0, data.train.z))
    assert drawn(light) < short_share(shorter.z, shorter.hit, shorter.nominal)
    np.testing.assert_array_equal(match_short_returns(beams, shorter, light).mass, light.mass)
