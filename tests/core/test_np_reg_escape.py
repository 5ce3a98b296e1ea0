"""A beam that meets nothing: NP-Reg's escape law reports nothing with the escape state's P(null), once.

Before the fix, ``escape()`` gave the escape segment the escape state's P(null) and ``prepare()``
applied it again, as to any segment: P(miss) = 1 - (1 - p)^2. On a real log whose beams often see
nothing within the map (Edmonton, 4 % nominal misses) NP-Reg, the binned histograms and mi-lidar
predicted 0.646 where 0.405 of those training beams missed, and their sampled scans missed as often.
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.densities import NPRegDensity
from mi_lidar.core.densities.histogram import fit_np_reg
from mi_lidar.core.densities.samples import protocol_residual_edges
from mi_lidar.planar.beams import base_model
from mi_lidar.planar.models import fine_grid

from ..conftest import rays_along_x
from .escaped_beams import escaped_beams

Z_MAX = 50.0  # m, the sensor's no-return value
ESCAPE_NULL = 0.4  # share of the beams that met nothing and reported nothing


def test_the_escape_segment_drops_with_the_escape_state_p_null():
    edges = protocol_residual_edges(Z_MAX)
    mass = np.ones((2, edges.size - 1))
    density = NPRegDensity(edges=edges, mass=mass, p_null=np.array([0.1, ESCAPE_NULL]), z_max=Z_MAX)
    rays = rays_along_x(8)
    seg = density.prepare(density.escape(rays), rays)
    np.testing.assert_allclose(np.asarray(seg.drop), ESCAPE_NULL, rtol=1e-6)


def planar_beams(n: int, seed: int):
    """``n`` beams at a wall (2 % no-returns) and ``n`` that meet nothing in the map (:data:`ESCAPE_NULL`
    no-returns, the rest anywhere up to :data:`Z_MAX`)."""
    return escaped_beams(n, seed, ESCAPE_NULL, lambda rng, size: rng.uniform(0.0, Z_MAX, size), wall_null=0.02)


def test_beams_that_meet_nothing_miss_as_often_as_the_training_beams_did():
    """Fitted NP-Reg on 4,000 beams (seed 0): P(miss) of a beam that met nothing is the training share of
    such beams that missed (exact: the escape state is not smoothed across states), and the sampler's miss
    rate over 5 x 2,000 such beams is within 4 standard errors of it (before: 0.64 for 0.40)."""
    samples, beams = planar_beams(2000, seed=0)
    density, _ = fit_np_reg(
        samples, fine_grid(samples), lambda d: 0.0, h_ranges=(1.0,), h_incidences=(20.0,), uniforms=(1e-3,), z_max=Z_MAX
    )
    model = base_model(density)
    escaped = ~np.isfinite(samples.nominal)
    trained = float(np.mean(~samples.hit[escaped]))
    np.testing.assert_allclose(beams.p_miss(model)[escaped], trained, rtol=1e-5)
    sampled = np.mean([np.mean(~beams.sample(model, seed)[1][escaped]) for seed in range(5)])
    standard_error = np.sqrt(trained * (1 - trained) / (5 * escaped.sum()))
    assert abs(sampled - trained) < 4 * standard_error, (sampled, trained)
