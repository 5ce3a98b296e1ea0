"""Why the demo's hit/miss F1 falls when the right dropout is added (the note it prints).

F1 compares one simulated draw with the log ray by ray. With measured hit rate q, a model that
always returns scores 2q/(1+q); the true dropout, drawn independently of the log's misses, scores
about q, lower, although its hit rate matches. Fixed seed; tolerance 0.01 on 20 000 rays.
"""

import numpy as np
import pytest

from mi_lidar.loop.compare import RayTable, metrics

Q = 0.93  # measured hit rate
N = 20_000


def table(measured_hit: np.ndarray, simulated_hit: np.ndarray) -> RayTable:
    zeros = np.zeros(N)
    return RayTable(
        ll=zeros,
        measured=np.where(measured_hit, 5.0, np.nan),
        hit=measured_hit,
        sim_range=np.where(simulated_hit, 5.0, np.nan),
        sim_hit=simulated_hit,
        nominal=zeros + 5,
        cos_incidence=zeros + 1,
        kind=np.zeros(N, int),
        label=np.zeros(N, int),
        shape=np.zeros(N, int),
        beam=np.zeros(N, int),
        column=np.arange(N),
        scan=np.zeros(N, int),
        azimuth=zeros,
    )


def test_always_returning_beats_the_true_dropout_on_f1_but_not_on_hit_rate():
    rng = np.random.default_rng(0)
    measured = rng.random(N) < Q
    always = metrics(table(measured, np.ones(N, bool)))
    true_model = metrics(table(measured, rng.random(N) < Q))
    assert always["f1"] == pytest.approx(2 * Q / (1 + Q), abs=0.01)
    assert true_model["f1"] == pytest.approx(Q, abs=0.01)
    assert always["f1"] > true_model["f1"]
    assert abs(true_model["hit_rate_simulated"] - Q) < 0.01 < abs(always["hit_rate_simulated"] - Q)
