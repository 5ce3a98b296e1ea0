"""NP-Reg's residual histograms give no mass outside ``[0, z_max]``, in the likelihood and the sampler alike.

A state's histogram is smoothed across range states, so a state near the sensor can hold mass at
residuals ``e < -r`` that no range reaches (the short returns of farther states), and a far state mass
beyond the farthest range the sensor reports (the long returns of nearer ones). The density is
truncated to ``[0, z_max]`` and renormalised: it integrates to one over the ranges a sensor reports,
and the sampler draws exactly that law (before the fix, 30 % of the draws at 1 m fell below 0 m and
came out as no-returns the likelihood did not predict; draws went past ``z_max``).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_lidar.core.densities import NPRegDensity
from mi_lidar.core.densities.base import escape_segment
from mi_lidar.core.densities.samples import protocol_residual_edges
from mi_lidar.core.segment import SURFACE

from ..conftest import rays_along_x

SHORT = 0.3  # share of the histogram at residuals -3..-2 m (unreachable from 1 m, reachable from 5 m)
STEP = 0.002  # m, the integration grid
DRAWS = 200_000


LONG = 0.2  # share of the long-tail histogram at residuals +6..+8 m
REACH = 8.0  # m, the support's end in the long-tail cases: cuts that tail at 1 m, and all of it at 5 m


def density(shape: str, long: bool = False) -> NPRegDensity:
    """A surface peak, with :data:`SHORT` of the mass at -3..-2 m, or with :data:`LONG` at +6..+8 m and the
    support ending at :data:`REACH`."""
    edges = protocol_residual_edges()
    centres = 0.5 * (edges[1:] + edges[:-1])
    peak = np.where(np.abs(centres) < 0.05, 1.0, 0.0)
    tail = (centres > 6) & (centres < 8) if long else (centres > -3) & (centres < -2)
    share = LONG if long else SHORT
    mass = (1.0 - share) * peak / peak.sum() + share * tail / tail.sum()
    z_max = REACH if long else 40.0
    return NPRegDensity(edges=edges, mass=mass[None, :].repeat(2, 0), p_null=np.zeros(2), shape=shape, z_max=z_max)


def lanes(r: float, n: int):
    rays = rays_along_x(n)
    at = dr.full(mi.Float, r, n)
    seg = escape_segment(rays).with_(kind=dr.full(mi.UInt32, SURFACE, n), nominal=at, mean=at)
    return seg, rays


@pytest.mark.parametrize("long", [False, True], ids=["short-tail", "long-tail"])
@pytest.mark.parametrize("shape", ["histogram", "polygon"])
@pytest.mark.parametrize("r", [1.0, 5.0])
def test_the_density_integrates_to_one_over_the_reported_ranges(shape, r, long):
    """Tolerance 2e-3: the grid's quadrature error on the 1 cm bins. With the long tail, nothing lies past
    the support's end (before the fix: 0.2 of the mass at 1 m, all the tail's, lay at 7-9 m)."""
    d = density(shape, long)
    z = np.arange(STEP / 2, 16.0, STEP)
    seg, rays = lanes(r, z.size)
    f = np.exp(np.asarray(d.log_prob(d.prepare(seg, rays), mi.Float(z.astype(np.float32)), rays), np.float64))
    assert abs(f.sum() * STEP - 1.0) < 2e-3, f.sum() * STEP
    if long:
        assert not np.any(f[z > REACH] > 1e-20)


@pytest.mark.parametrize("long", [False, True], ids=["short-tail", "long-tail"])
@pytest.mark.parametrize("shape", ["histogram", "polygon"])
@pytest.mark.parametrize("r", [1.0, 5.0])
def test_draws_follow_the_truncated_density(shape, r, long):
    """200,000 draws (fixed seed): none below 0 m or past the support's end, and the 5 cm histogram of the
    draws is within 0.01 of the density's in total variation (sampling noise alone is about 0.003)."""
    d = density(shape, long)
    seg, rays = lanes(r, DRAWS)
    rng = np.random.default_rng(3)
    u = mi.Point2f(*(mi.Float(rng.random(DRAWS, dtype=np.float32)) for _ in range(2)))
    drawn = np.asarray(d.sample(d.prepare(seg, rays), u, rays), np.float64)
    assert drawn.min() >= 0.0
    assert drawn.max() <= float(d["z_max"][0]) + 1e-4
    bins = np.arange(0.0, 16.0 + 1e-9, 0.05)
    z = np.arange(STEP / 2, 16.0, STEP)
    seg_z, rays_z = lanes(r, z.size)
    f = np.exp(np.asarray(d.log_prob(d.prepare(seg_z, rays_z), mi.Float(z.astype(np.float32)), rays_z), np.float64))
    expected = np.histogram(z, bins=bins, weights=f * STEP)[0]
    observed = np.histogram(drawn, bins=bins)[0] / DRAWS
    assert 0.5 * np.abs(observed - expected).sum() < 0.01
