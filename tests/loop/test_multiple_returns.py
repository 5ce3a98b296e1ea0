"""Multiple returns: the sampler's first and last echoes follow the likelihood's distribution.

Where every sub-ray of a beam meets an opaque surface first (all rays of the room but those
through its glass pane), the ``first`` and ``last`` likelihoods of
:class:`~mi_lidar.core.effects.multiple_returns.MultipleReturns` are exact. For 60 simulated scans
(fixed seeds) the probability integral transform of every return under the likelihood (its CDF,
integrated by the trapezoid rule on a 1 mm grid) must be uniform: Kolmogorov-Smirnov distance below 0.02 over about
20 000
returns (the 1 % critical value is 0.012; the grid and float32 add a few thousandths).
"""

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_lidar.core.effects import parse_effects
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import mixture_log_likelihood
from mi_lidar.core.rays import LogRays
from mi_lidar.core.trace import trace_rounds
from mi_lidar.scene.simulation import simulate

from .helpers import room

SEEDS = 60


def pit(scene, model, logs) -> tuple[np.ndarray, np.ndarray]:
    """CDF of every simulated return under the model's likelihood (seeds x rays), and the rays
    whose five sub-rays all meet an opaque first element (where the likelihood is exact)."""
    rays = LogRays.from_log(logs[0])
    batch, _, hit = rays.batch()
    table = ElementTable.from_scene(scene)
    rounds = trace_rounds(scene, table, model, batch)
    first = rounds.rounds[0]  # sub-rays: lane j n + i is sub-ray j of beam i
    p_first = np.zeros(rounds.width)
    p_first[np.asarray(first.ray)] = np.asarray(dr.gather(mi.Float, table.p_hit, first.element))
    opaque = np.all(p_first.reshape(-1, rays.n) == 1.0, axis=0)
    ranges = np.stack([log.ranges.ravel() for log in logs])
    grid = np.arange(ranges.min() - 0.2, ranges.max() + 0.2, 0.001)
    density = np.stack(
        [
            np.exp(
                np.asarray(
                    mixture_log_likelihood(table, model, batch, rounds, mi.Float(np.full(rays.n, g, np.float32)), hit)
                )
            )
            for g in grid
        ]
    )
    cdf = np.concatenate([np.zeros((1, rays.n)), np.cumsum(0.5 * (density[1:] + density[:-1]), axis=0)])
    cdf /= cdf[-1]  # trapezoid rule, then linear interpolation between grid points
    index = np.clip(np.searchsorted(grid, ranges), 1, grid.size - 1)
    frac = (ranges - grid[index - 1]) / (grid[index] - grid[index - 1])
    low, high = np.take_along_axis(cdf, index - 1, axis=0), np.take_along_axis(cdf, index, axis=0)
    return low + frac * (high - low), opaque


@pytest.mark.parametrize("mode", ["first", "last"])
def test_first_and_last_echo_follow_the_likelihood(mode):
    scene, model, poses = room(1)
    true = dataclasses.replace(model, effects=parse_effects(f"multiple_returns(mode={mode}, divergence=0.03)"))
    logs = [simulate(scene, poses=poses, model=true, seed=s) for s in range(SEEDS)]
    assert all(log.hit.all() for log in logs)
    u, opaque = pit(scene, true, logs)
    assert opaque.mean() > 0.8  # the glass pane (p_hit 0.3) is the exception
    u = np.sort(u[:, opaque].ravel())
    ks = np.max(np.abs(u - (np.arange(u.size) + 0.5) / u.size))
    assert ks < 0.02, ks
    # The echoes differ from the axis ray's range where the footprint straddles two walls.
    axis = dataclasses.replace(model, effects=[])
    plain = simulate(scene, poses=poses, model=axis, seed=0).ranges.ravel()
    spread = np.mean([log.ranges.ravel() for log in logs], axis=0) - plain
    assert (np.min(spread) < -0.02) if mode == "first" else (np.max(spread) > 0.02)


def test_strongest_echo_is_the_majority_surface():
    """Straight at a wall every echo merges: strongest equals the energy-weighted return."""
    scene, model, poses = room(1)
    strongest = dataclasses.replace(model, effects=parse_effects("multiple_returns(mode=strongest, divergence=0.001)"))
    log = simulate(scene, poses=poses, model=strongest, seed=3)
    plain = simulate(scene, poses=poses, model=dataclasses.replace(model, effects=[]), seed=3)
    assert log.hit.all()
    assert np.median(np.abs(log.ranges - plain.ranges)) < 0.03
    dr.sync_thread()
