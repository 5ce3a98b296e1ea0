"""NP-Reg's support ends where the sensor's returns end, chosen by held-out likelihood.

The long tail that the kernel shares across states (a door seen open at 2 m, +8 m) let a fitted
NP-Reg draw returns far beyond anything the sensor reported (on the Intel log, 73 of 32,760 sampled
test returns past 26 m, where the sensor never reported beyond 25.4 m; histogram match 0.122 m).
:func:`fit_np_reg` now ends the support at a multiple of the farthest training return, chosen on
held-out beams among :data:`REACHES` (infinite: the sensor's ``z_max``, as before).
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from mi_lidar.core.densities.histogram import fit_np_reg, support_end
from mi_lidar.core.densities.samples import StateSamples
from mi_lidar.planar.beams import base_model, nominal_beams
from mi_lidar.planar.models import fine_grid

Z_MAX = 80.0  # m, the sensor's largest range
LONG = 0.05  # share of the returns that come from up to 10 m behind the wall


def wall_beams(n: int, seed: int, farther: float = 0.0):
    """``n`` beams at a wall 1-10 m away (2 cm noise, 2 % no-returns, :data:`LONG` of the returns up to
    10 m behind it, the last ``farther`` of those up to 14 m), as state samples and as the engine's beams."""
    rng = np.random.default_rng(seed)
    nominal = rng.uniform(1.0, 10.0, n)
    hit = rng.random(n) > 0.02
    behind = rng.uniform(0.5, 10.0, n)
    behind[: int(farther * n)] = rng.uniform(10.0, 14.0, int(farther * n))
    z = np.where(rng.random(n) < LONG, nominal + behind, nominal + rng.normal(0.0, 0.02, n))
    z = np.where(hit, z, np.nan)
    incidence, beam = np.full(n, np.nan), np.zeros(n, np.int64)
    samples = StateSamples(nominal=nominal, incidence=incidence, beam=beam, label=beam, z=z, hit=hit)
    trace = SimpleNamespace(
        n=n, nominal=nominal, incidence=incidence, hit=hit, z=z, beam=beam, scan=np.arange(n) // 100
    )
    return samples, nominal_beams(trace)


def fitted(samples: StateSamples, held_out_beams, reaches=None):
    def held_out(density) -> float:
        return float(-np.mean(held_out_beams.log_likelihood(base_model(density))))

    options = {} if reaches is None else {"reaches": reaches}
    return fit_np_reg(
        samples, fine_grid(samples), held_out, h_ranges=(1.0,), h_incidences=(20.0,), z_max=Z_MAX, **options
    )


def test_the_support_ends_near_the_farthest_return_and_no_draw_passes_it():
    """6,000 training and 6,000 held-out beams (seeds 0, 1): the chosen support ends within 1.5x the farthest
    training return (20 m at most), and none of 5 sampled scans of the held-out beams returns past it.
    With the support at z_max (the old fit), the same draws pass 22 m (so the test can fail)."""
    samples, _ = wall_beams(6000, seed=0)
    _, check = wall_beams(6000, seed=1)
    density, table = fitted(samples, check)
    farthest = float(np.nanmax(samples.z))
    end = float(density["z_max"][0])
    assert farthest <= end <= 1.5 * farthest, (farthest, end)
    reach_rows = [row for row in table if row[4] == 1.0]  # before P(no return)'s own bandwidth is tried
    assert len(reach_rows) == 5 and {row[3] for row in reach_rows} == {1.0, 1.1, 1.25, 1.5, math.inf}
    drawn = np.concatenate([check.sample(base_model(density), seed)[0] for seed in range(5)])
    assert np.nanmax(drawn) <= end + 1e-3
    wide, _ = fitted(samples, check, reaches=(math.inf,))
    assert float(wide["z_max"][0]) == Z_MAX
    drawn_wide = np.concatenate([check.sample(base_model(wide), seed)[0] for seed in range(5)])
    assert np.nanmax(drawn_wide) > 22.0


def test_held_out_returns_beyond_the_training_ones_keep_a_margin():
    """Held-out beams whose long returns reach 14 m behind the wall (1 % of them) where the training ones
    reach 10 m: the chosen support covers every held-out return, and it scores better held out than
    both the farthest training return alone and the sensor's z_max."""
    samples, _ = wall_beams(6000, seed=0)
    _, check = wall_beams(6000, seed=1, farther=0.01)
    density, table = fitted(samples, check)
    end = float(density["z_max"][0])
    assert end >= float(np.nanmax(check.z)), (end, float(np.nanmax(check.z)))
    nll = {row[3]: row[-1] for row in table}
    assert min(nll.values()) < nll[1.0] and min(nll.values()) < nll[math.inf]
    assert math.isclose(end, support_end(samples, min(nll, key=nll.get), Z_MAX), rel_tol=1e-6)
