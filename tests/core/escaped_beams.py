"""Synthetic planar beams, half at a wall and half meeting nothing in the map: the escape laws' test data."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from mi_lidar.core.densities.samples import StateSamples
from mi_lidar.planar.beams import nominal_beams


def escaped_beams(n: int, seed: int, escape_null: float, escaped_returns, wall_null: float = 0.0):
    """``n`` beams at a wall (1-10 m, 2 cm noise, ``wall_null`` no-returns) and ``n`` that meet nothing in
    the map (``escape_null`` no-returns, the others at ``escaped_returns(rng, size)`` m).

    Returns:
        The state samples and the engine's beams (a trace stand-in with the fields
        :func:`~mi_lidar.planar.beams.nominal_beams` reads), beams at the wall first.
    """
    rng = np.random.default_rng(seed)
    nominal = np.concatenate([rng.uniform(1.0, 10.0, n), np.full(n, np.nan)])
    hit = np.concatenate([rng.random(n) > wall_null, rng.random(n) > escape_null])
    z = np.where(np.isfinite(nominal), nominal + rng.normal(0.0, 0.02, 2 * n), escaped_returns(rng, 2 * n))
    z = np.where(hit, z, np.nan)
    incidence = np.full(2 * n, np.nan)
    beam = np.zeros(2 * n, np.int64)
    samples = StateSamples(nominal=nominal, incidence=incidence, beam=beam, label=beam, z=z, hit=hit)
    trace = SimpleNamespace(
        n=2 * n, nominal=nominal, incidence=incidence, hit=hit, z=z, beam=beam, scan=np.arange(2 * n) // 100
    )
    return samples, nominal_beams(trace)
