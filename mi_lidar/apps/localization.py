"""Particle-filter localization (Monte Carlo localization) with the likelihood-field model.

Particles start around a noisy initial guess (uniform in a 0.5 m disc and +-10 deg), move with the
(noisy) odometry motion plus the filter's own motion noise (:func:`~mi_lidar.apps.scans.motion_sigma`),
and are weighted by the likelihood field of the state's map: each used beam's endpoint contributes
``log(z_hit N(d; 0, sigma_hit) + z_rand / z_max)`` with ``d`` the distance (m) from the endpoint to the
nearest occupied cell, ``z_hit = 1 - z_rand`` and ``z_max`` :data:`~mi_lidar.apps.scans.REACH`; beams
without a return are skipped. The estimate is the weighted mean; particles are resampled (low
variance) after every update.

==============  =======================================================  ====
alpha           meaning                                                  unit
==============  =======================================================  ====
``particles``   number of particles                                      -
``sigma_hit``   the filter's range noise of the likelihood field         m
``z_rand``      the filter's weight of random readings                   -
==============  =======================================================  ====

``J``: the mean position error (m) over states and runs, each state's error capped at
:data:`~mi_lidar.apps.scans.CAP` m so a lost filter counts as lost, not as its distance. Also reported: the divergence
rate (share of states with error > 1 m) and the mean heading error (deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from mi_lidar.apps.risk import Parameter
from mi_lidar.apps.scans import CAP, REACH, PlanarStates, compose, motion_sigma, noisy_run, wrap

FIELD_CLIP = 2.55  # m: the distance field is kept in whole centimetres up to this


def distance_field(occupancy: np.ndarray, cell: float) -> np.ndarray:
    """(nx, ny) uint8 distance (cm, clipped at :data:`FIELD_CLIP`) from each cell centre to the nearest occupied one."""
    if not occupancy.any():
        return np.full(occupancy.shape, 255, np.uint8)
    d = distance_transform_edt(~occupancy) * cell
    return np.round(np.minimum(d, FIELD_CLIP) * 100).astype(np.uint8)


def endpoint_distance(field: np.ndarray, grid, points: np.ndarray) -> np.ndarray:
    """(...,) distance (m) from world ``points`` (..., 2) to the map (:data:`FIELD_CLIP` outside the grid)."""
    flat = grid.cell_of(points)
    return np.where(flat >= 0, field.ravel()[np.maximum(flat, 0)] / 100.0, FIELD_CLIP)


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``len(weights)`` particles drawn by systematic (low-variance) resampling of normalised weights."""
    n = weights.size
    positions = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(np.cumsum(weights), positions), n - 1)


@dataclass
class ParticleFilter:
    """The localization application (see the module docstring).

    Attributes:
        runs: filter runs per evaluation (each with its own noise, the same on every dataset).
        beams: beams used per update (evenly spread; the likelihood field's usual subsampling).
        seed: seed of the first run.
    """

    runs: int = 3
    beams: int = 60
    seed: int = 0
    name: str = "localization"
    objective: str = f"MCL mean position error, capped at {CAP:g} m (m)"
    parameters: tuple[Parameter, ...] = (
        Parameter("particles", (25.0, 50.0, 100.0, 200.0, 400.0, 800.0), start=50.0),
        Parameter("sigma_hit", (0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8), start=0.01, unit="m"),
        Parameter("z_rand", (0.001, 0.01, 0.05, 0.1, 0.2, 0.4), start=0.001),
    )

    @staticmethod
    def field(states: PlanarStates, t: int) -> np.ndarray:
        """The distance field of state ``t``'s map (built once per states)."""
        return states.memo(("field", t), lambda: distance_field(states.maps.occupancy(t), states.maps.grid.cell))

    def evaluate(self, alpha: dict, states: PlanarStates, ranges: np.ndarray) -> dict:
        """Run the filter ``runs`` times on ``ranges`` (T, N) with setting ``alpha``."""
        n = int(alpha["particles"])
        sigma, z_rand = alpha["sigma_hit"], alpha["z_rand"]
        used = np.unique(np.linspace(0, states.angles.size - 1, min(self.beams, states.angles.size)).astype(int))
        cos, sin = np.cos(states.angles[used]), np.sin(states.angles[used])
        floor = z_rand / REACH
        errors, headings = [], []
        for run in range(self.runs):
            guess, motions = noisy_run(states, self.seed + run)
            rng = np.random.default_rng(10_000 + self.seed + run)
            radius, bearing = 0.5 * np.sqrt(rng.random(n)), rng.uniform(-np.pi, np.pi, n)
            particles = guess + np.stack(
                [radius * np.cos(bearing), radius * np.sin(bearing), rng.uniform(-1, 1, n) * np.radians(10.0)], 1
            )
            for t in range(states.n):
                if t > 0:
                    u = motions[t - 1]
                    particles = compose(particles, u + rng.normal(0.0, 1.0, (n, 3)) * motion_sigma(u))
                r = ranges[t, used]
                ok = np.isfinite(r) & (r > 0) & (r < REACH)
                log_w = np.zeros(n)
                if ok.any():
                    lx, ly = r[ok] * cos[ok], r[ok] * sin[ok]
                    c, s = np.cos(particles[:, 2:3]), np.sin(particles[:, 2:3])
                    ends = np.stack([particles[:, :1] + c * lx - s * ly, particles[:, 1:2] + s * lx + c * ly], -1)
                    d = endpoint_distance(self.field(states, t), states.maps.grid, ends)
                    p = (1.0 - z_rand) * np.exp(-0.5 * (d / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma) + floor
                    log_w = np.log(p).sum(axis=1)
                w = np.exp(log_w - log_w.max())
                w /= w.sum()
                heading = np.arctan2(w @ np.sin(particles[:, 2]), w @ np.cos(particles[:, 2]))
                estimate = np.array([w @ particles[:, 0], w @ particles[:, 1], heading])
                truth = states.poses[t]
                errors.append(float(np.hypot(*(estimate[:2] - truth[:2]))))
                headings.append(float(abs(wrap(estimate[2] - truth[2]))))
                particles = particles[low_variance_resample(w, rng)]
        errors_np = np.asarray(errors)
        return {
            "J": float(np.mean(np.minimum(errors_np, CAP))),
            "divergence": float(np.mean(errors_np > 1.0)),
            "heading_error_deg": float(np.degrees(np.mean(headings))),
            "error_median": float(np.median(errors_np)),
        }
