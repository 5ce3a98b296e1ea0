"""Particle-filter localization (Monte Carlo localization) with the likelihood-field model, along the whole log.

The filter runs along every scan of the log, stretch after stretch (about 20 m of travel each). At the
start of a stretch the particles are spread around a noisy guess (uniform in a 0.5 m disc and +-10 deg
around the noisy start pose of :func:`~mi_lidar.apps.scans.noisy_runs`); they move with the
(noisy) odometry motion plus the filter's own motion noise (:func:`~mi_lidar.apps.scans.motion_sigma`),
and are weighted by the likelihood field of the state's leave-out map: each used beam's endpoint
contributes ``log(z_hit N(d; 0, sigma_hit) + z_rand / z_max)`` with ``d`` the distance (m) from the
endpoint to the nearest occupied cell, ``z_hit = 1 - z_rand`` and ``z_max``
:data:`~mi_lidar.apps.scans.REACH`; beams without a return are skipped. The estimate is the weighted
mean; particles are resampled (low variance) after every update. The runs of one evaluation are
filtered side by side; run ``r`` has the same noise on every dataset (its own random stream for the
odometry, the particles and the resampling) and sees a simulator's ``r``-th sampled scans.

==============  =======================================================  ====
alpha           meaning                                                  unit
==============  =======================================================  ====
``particles``   number of particles                                      -
``sigma_hit``   the filter's range noise of the likelihood field         m
``z_rand``      the filter's weight of random readings                   -
==============  =======================================================  ====

``J``: the mean position error (m) over states and runs, each state's error capped at
:data:`~mi_lidar.apps.scans.CAP` m so a lost filter counts as lost, not as its distance; runs are added
while its standard error exceeds ``target_se`` (up to ``max_runs``). Also reported: the divergence
rate (share of states with error > 1 m) and the mean heading error (deg).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.ndimage import distance_transform_edt

from mi_lidar.apps.risk import Parameter
from mi_lidar.apps.scans import (
    CAP,
    REACH,
    PlanarStates,
    Tracker,
    compose,
    motion_sigma,
    noisy_runs,
    run_ranges,
    stretch_mask,
    stretches,
    tracker_metrics,
    wrap,
)

FIELD_CLIP = 2.55  # m: the distance field is kept in whole centimetres up to this


def distance_field(occupancy: np.ndarray, cell: float) -> np.ndarray:
    """(nx + 2, ny + 2) uint8 distance (cm, at most :data:`FIELD_CLIP`) from each cell centre to the nearest occupied.

    The grid is padded by one cell of :data:`FIELD_CLIP` on every side: what lies outside the grid is far from the map.
    """
    field = np.full((occupancy.shape[0] + 2, occupancy.shape[1] + 2), round(FIELD_CLIP * 100), np.uint8)
    if occupancy.any():
        d = distance_transform_edt(~occupancy) * cell
        field[1:-1, 1:-1] = np.round(np.minimum(d, FIELD_CLIP) * 100).astype(np.uint8)
    return field


def endpoint_distance(field: np.ndarray, grid, points: np.ndarray) -> np.ndarray:
    """(...,) uint8 distance (cm) from world ``points`` (..., 2) to the map, from a padded :func:`distance_field`."""
    nx, ny = field.shape
    i = np.clip(np.floor((points[..., 0] - grid.origin[0]) / grid.cell), -1, nx - 2).astype(np.intp) + 1
    j = np.clip(np.floor((points[..., 1] - grid.origin[1]) / grid.cell), -1, ny - 2).astype(np.intp) + 1
    return field.ravel()[i * ny + j]


def low_variance_resample(weights: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Systematic (low-variance) resampling of each row of normalised ``weights`` (R, n) with its offset in [0, 1) (R,).

    Returns:
        (R, n) indices of the drawn particles within each row.
    """
    runs, n = weights.shape
    rows = np.arange(runs)[:, None]
    cumulative = np.cumsum(weights, axis=1)
    cumulative /= cumulative[:, -1:]
    positions = (offsets[:, None] + np.arange(n)) / n
    picks = np.searchsorted((cumulative + rows).ravel(), (positions + rows).ravel()).reshape(runs, n) - rows * n
    return np.clip(picks, 0, n - 1)


@dataclass
class ParticleFilter(Tracker):
    """The localization application (see the module docstring; run settings: :class:`~mi_lidar.apps.scans.Tracker`).

    Attributes:
        beams: beams used per update (evenly spread; the likelihood field's usual subsampling).
        seed: seed of the runs' noise.
    """

    beams: int = 60
    seed: int = 0
    sweep: ClassVar[str] = "particles"  # the parameter swept at the best real setting (thesis fig. 3.20)
    effort: ClassVar[str] = "divergence"  # the metric shown beside J along the sweep
    name: str = "localization"
    objective: str = f"MCL mean position error, capped at {CAP:g} m (m)"
    parameters: tuple[Parameter, ...] = (
        Parameter("particles", (25.0, 50.0, 100.0, 200.0, 400.0, 800.0), start=50.0),
        Parameter("sigma_hit", (0.01, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8), start=0.01, unit="m"),
        Parameter("z_rand", (0.001, 0.01, 0.05, 0.1, 0.2, 0.4), start=0.001),
    )

    @staticmethod
    def field(states: PlanarStates, t: int) -> np.ndarray:
        """The distance field of state ``t``'s map (built once per map)."""
        g = states.maps.map_of(t)
        return states.memo(("field", g), lambda: distance_field(states.maps.occupancy(t), states.maps.grid.cell))

    def filter(self, alpha: dict, states: PlanarStates, ranges: np.ndarray, indices: np.ndarray) -> dict:
        """Run the filter along the states for run indices ``indices`` (R,); per-run arrays of what it did."""
        n, runs = int(alpha["particles"]), len(indices)
        sigma, z_rand = alpha["sigma_hit"], alpha["z_rand"]
        used = np.unique(np.linspace(0, states.angles.size - 1, min(self.beams, states.angles.size)).astype(int))
        data = run_ranges(ranges, indices)[:, :, used]
        cos, sin = np.cos(states.angles[used]), np.sin(states.angles[used])
        starts, motions = noisy_runs(states, indices, self.seed)
        streams = [np.random.default_rng([self.seed, int(run), 1]) for run in indices]
        errors, headings = np.empty((runs, states.n)), np.empty((runs, states.n))
        # log-likelihood of one endpoint at each distance of the field (whole centimetres)
        d = np.arange(256) / 100.0
        table = np.log((1.0 - z_rand) * np.exp(-0.5 * (d / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma) + z_rand / REACH)
        cuts = stretches(states, self.stretch, self.max_states)
        for first, stop in cuts:
            radius = 0.5 * np.sqrt(np.stack([g.random(n) for g in streams]))
            bearing = np.stack([g.uniform(-np.pi, np.pi, n) for g in streams])
            turn = np.stack([g.uniform(-1.0, 1.0, n) for g in streams]) * np.radians(10.0)
            spread = np.stack([radius * np.cos(bearing), radius * np.sin(bearing), turn], axis=-1)
            particles = starts[:, first][:, None, :] + spread
            for t in range(first, stop):
                if t > first:
                    u = motions[:, t - 1][:, None, :]
                    jitter = np.stack([g.normal(0.0, 1.0, (n, 3)) for g in streams])
                    particles = compose(particles, u + jitter * motion_sigma(u))
                r = data[:, t]  # (R, B)
                ok = np.isfinite(r) & (r > 0) & (r < REACH)
                lx, ly = np.where(ok, r, 0.0) * cos, np.where(ok, r, 0.0) * sin
                c, s = np.cos(particles[..., 2:3]), np.sin(particles[..., 2:3])  # (R, n, 1)
                ends = np.stack(
                    [
                        particles[..., :1] + c * lx[:, None] - s * ly[:, None],
                        particles[..., 1:2] + s * lx[:, None] + c * ly[:, None],
                    ],
                    axis=-1,
                )
                d = endpoint_distance(self.field(states, t), states.maps.grid, ends)  # (R, n, B)
                log_w = np.sum(table[d] * ok[:, None, :], axis=2)
                w = np.exp(log_w - log_w.max(axis=1, keepdims=True))
                w /= w.sum(axis=1, keepdims=True)
                heading = np.arctan2(np.sum(w * np.sin(particles[..., 2]), 1), np.sum(w * np.cos(particles[..., 2]), 1))
                x, y = np.sum(w * particles[..., 0], 1), np.sum(w * particles[..., 1], 1)
                errors[:, t] = np.hypot(x - states.poses[t, 0], y - states.poses[t, 1])
                headings[:, t] = np.abs(wrap(heading - states.poses[t, 2]))
                picks = low_variance_resample(w, np.array([g.random() for g in streams]))
                particles = np.take_along_axis(particles, picks[..., None], axis=1)
        used = stretch_mask(cuts, states.n)
        errors, headings = errors[:, used], headings[:, used]
        return {"objective": np.minimum(errors, CAP).mean(axis=1), "errors": errors, "headings": headings}

    def evaluate(self, alpha: dict, states: PlanarStates, ranges: np.ndarray) -> dict:
        """Run the filter along the states on ``ranges`` ((S, T, N) or (T, N)) with setting ``alpha``."""
        done = self.filter_runs(alpha, states, ranges)
        return {
            **tracker_metrics(done),
            "error_median": float(np.median(done["errors"])),
        }
