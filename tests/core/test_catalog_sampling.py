"""Every catalog effect (each variant) and every density samples what it scores.

For one scan of the street (a VLP-16 pattern of 12 firings, 192 rays) the sampler draws 200 scans
from the same pose (independent: every scan has its own ray ids) under the case's truth; the
likelihood's density of each ray is integrated on a 5 mm grid over 0-40 m into 5 cm bins, plus its
miss probability. Pooled over the rays, the expected bin counts are compared with the sampled ones
by the total-variation distance. Sampling noise alone gives about 0.01-0.02 here; the tolerance is
0.04, and 0.08 for the effects whose likelihood is a documented approximation (the footprint
effects' moment matching, quantization's continuous stand-in); ``multiple_returns(mode=strongest)``
is held to 0.25 only (see LOOSE). The miss fraction must agree to 0.02.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

import mi_lidar
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import mixture_log_likelihood
from mi_lidar.core.patterns import get_pattern
from mi_lidar.core.rays import LogRays
from mi_lidar.core.trace import trace_rounds

from .catalog import case_ids, label, make_part, model_with, street

APPROXIMATE = {"mixed_pixels", "multiple_returns", "quantization"}
# multiple_returns(mode=strongest) scores with the first echo's density: behind permeable tree crowns the
# strongest echo group is often the farther one, and the distance measured here is 0.19 (a known limit).
LOOSE = {"multiple_returns-strongest": 0.25}
SEEDS, STEP, BIN, TOP = 200, 0.005, 0.05, 40.0
CASES = case_ids()


def expected_distribution(scene, model, log) -> tuple[np.ndarray, float]:
    """(bin probabilities over 0-40 m, mean miss probability) of the first scan's rays under ``model``."""
    rays = LogRays.from_log(log)
    n = rays.n
    grid = np.arange(STEP / 2, TOP, STEP)
    table = ElementTable.from_scene(scene)
    batch, _, _ = rays.batch(np.repeat(np.arange(n), grid.size))
    rounds = trace_rounds(scene, table, model, batch)
    z = mi.Float(np.tile(grid, n).astype(np.float32))
    density = np.exp(np.asarray(mixture_log_likelihood(table, model, batch, rounds, z, mi.Bool(True) | (z < 0))))
    per_bin = density.reshape(n, -1, int(round(BIN / STEP))).sum(axis=2) * STEP
    single, _, _ = rays.batch(np.arange(n))
    miss = np.exp(
        np.asarray(
            mixture_log_likelihood(
                table,
                model,
                single,
                trace_rounds(scene, table, model, single),
                mi.Float(np.zeros(n, np.float32)),
                mi.Bool(np.zeros(n, bool)),
            )
        )
    )
    return per_bin.mean(axis=0), float(miss.mean())


@pytest.mark.parametrize("case", CASES, ids=[label(c) for c in CASES])
def test_samples_follow_the_density(case):
    scene, model, _, poses = street()
    pattern = get_pattern("vlp16", n_firings=12)
    truth = model_with(model, case, make_part(case, 0.0, pattern.shape[0], 8))
    log = mi_lidar.simulate(scene, pattern, poses=np.repeat(poses[:1], SEEDS, 0), seed=7, model=truth)
    ranges, hits = log.ranges.ravel(), log.hit.ravel()
    observed = np.histogram(ranges[hits], bins=np.arange(0.0, TOP + BIN / 2, BIN))[0] / hits.size
    expected, miss = expected_distribution(scene, truth, log.scan(0))
    tv = 0.5 * (np.abs(observed - expected).sum() + abs((1 - hits.mean()) - miss))
    tolerance = LOOSE.get(label(case), 0.08 if case[1] in APPROXIMATE else 0.04)
    assert abs((1 - hits.mean()) - miss) < 0.02, (1 - hits.mean(), miss)
    assert tv < tolerance, f"total variation {tv:.4f}"
