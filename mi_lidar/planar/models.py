"""The baselines the planar benchmark compares with mi-lidar, each fitted on training beams only and scored by the
one engine.

=========  ===================================================================================
name       model (``docs/benchmark_planar.md``)
=========  ===================================================================================
M0         ideal ray cast + one Gaussian (Gazebo-style): sigma by 1-D search, P(miss) 1e-3 at a
           nominal hit; a nominal-miss beam returns (uniformly on [0, z_max]) with the training
           frequency (the protocol scores such returns 1e-3, an improper density; this keeps M0 proper)
M1         Probabilistic Robotics beam mixture, 6 global parameters (the one Adam fitter)
M2a, M2b   the same per nominal-range bin / per range x incidence bin; bins with < 300 training
           beams fall back to the range bin, then to M1
M3a, M3b   residual histograms per bin with the protocol's smoothing (the binned NP baseline)
P-Reg      thesis 3.3: P_null, mean, sigma by local linear kernel regression on range and incidence
NP-Reg     thesis 3.4: per-state histograms smoothed across states by a kernel (frequency polygon)
mi-lidar   the permeable map (:mod:`mi_lidar.planar.permeable`)
=========  ===================================================================================

P-Reg's and NP-Reg's bandwidths are chosen on the training scans only: every other training scan is held out
for the choice, and the model is refitted on all training scans with the chosen setting.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mi_lidar.core.densities import BeamDensity, PhysicsDensity
from mi_lidar.core.densities.histogram import fit_binned_histogram, fit_np_reg
from mi_lidar.core.densities.preg import fit_p_reg
from mi_lidar.core.densities.samples import StateSamples, protocol_residual_edges
from mi_lidar.core.densities.tables import StateGrid
from mi_lidar.core.problem import fit_parts
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.planar.beams import EngineBeams, base_model, golden_section, nominal_beams
from mi_lidar.planar.trace import PlanarTrace

RANGE_EDGES = [float(e) for e in np.linspace(0.0, 40.0, 18)] + [1.0e9]  # 17 bins over 0-40 m (M2a, M3a)
INCIDENCE_EDGES = [0.0, 20.0, 40.0, 55.0, 65.0, 75.0, 82.0, 90.0]  # plus the unknown bin (M2b, M3b)
MIN_BEAMS = 300


def samples_of(trace: PlanarTrace) -> StateSamples:
    """The nominal state of every beam and its measurement."""
    return StateSamples(
        nominal=trace.nominal,
        incidence=trace.incidence,
        beam=trace.beam,
        label=np.zeros(trace.n, np.int64),
        z=trace.z,
        hit=trace.hit,
    )


def fit_m0(train: EngineBeams, samples: StateSamples, z_max: float) -> SensorModel:
    """M0: sigma by golden-section search on the training NLL (the one score)."""
    escaped = ~samples.met
    escape = float(np.clip(samples.hit[escaped].mean() if escaped.any() else 0.0, 1e-3, 1.0 - 1e-3))

    def density(log_sigma: float) -> PhysicsDensity:
        return PhysicsDensity(sigma0=float(np.exp(log_sigma)), k=0.0, p_null=1e-3, escape_return=escape, z_max=z_max)

    def nll(log_sigma: float) -> float:
        return float(-np.mean(train.log_likelihood(base_model(density(log_sigma)))))

    return base_model(density(golden_section(nll, np.log(0.003), np.log(2.0))))


def fit_beam(
    train: EngineBeams,
    samples: StateSamples,
    grid: StateGrid,
    z_max: float,
    start: BeamDensity | None,
    fallback: Callable[[np.ndarray], np.ndarray] | None,
    steps: int = 150,
) -> SensorModel:
    """M1 / M2: the beam mixture on ``grid`` by the one fitter; thin states take ``fallback``'s parameters."""
    density = BeamDensity(grid=grid, z_max=z_max, escape="shared" if grid.size == 1 else "own")
    if start is not None:  # start every state from the coarser model
        for key in ("logits", "log_sigma", "log_lambda"):
            width = 4 if key == "logits" else 1
            parent = np.asarray(start.params[key]).reshape(-1, width)
            density.params[key] = type(density.params[key])(np.tile(parent[0], grid.size + 1).astype(np.float32))
    model = base_model(density)
    fit_parts(model, train.problem(), [density], steps=steps)
    if fallback is not None:
        met = samples.met
        state = np.full(samples.n, grid.size)
        state[met] = grid.index_np(samples.nominal[met], samples.incidence[met])
        thin = np.bincount(state, minlength=grid.size + 1) < MIN_BEAMS
        for key in ("logits", "log_sigma", "log_lambda"):
            width = 4 if key == "logits" else 1
            values = np.asarray(density.params[key]).reshape(-1, width).copy()
            values[thin] = fallback(key)[thin]
            density.params[key] = type(density.params[key])(values.ravel().astype(np.float32))
    return model


def fit_beam_family(train: EngineBeams, samples: StateSamples, z_max: float) -> dict[str, SensorModel]:
    """M1, M2a and M2b with the protocol's fall-backs."""
    m1 = fit_beam(train, samples, StateGrid(), z_max, None, None)
    one = m1.density

    def global_values(key: str) -> np.ndarray:
        width = 4 if key == "logits" else 1
        row = np.asarray(one.params[key]).reshape(-1, width)[0]
        return np.tile(row, (len(RANGE_EDGES) - 1 + 1, 1)) if key else row

    range_grid = StateGrid(range_edges=RANGE_EDGES)
    m2a = fit_beam(train, samples, range_grid, z_max, one, global_values)
    both_grid = StateGrid(range_edges=RANGE_EDGES, incidence_edges=INCIDENCE_EDGES)

    def range_values(key: str) -> np.ndarray:
        width = 4 if key == "logits" else 1
        per_range = np.asarray(m2a.density.params[key]).reshape(-1, width)  # (R + 1, width), escape last
        inner = np.tile(per_range[:-1], (both_grid.n_incidence, 1))  # StateGrid order: incidence-major
        return np.concatenate([inner, per_range[-1:]])

    m2b = fit_beam(train, samples, both_grid, z_max, one, range_values)
    return {"M1": m1, "M2a": m2a, "M2b": m2b}


def fit_histograms(samples: StateSamples, z_max: float) -> dict[str, SensorModel]:
    """M3a and M3b: the protocol's binned histograms."""
    edges = protocol_residual_edges(z_max)
    out = {}
    for name, grid in (
        ("M3a", StateGrid(range_edges=RANGE_EDGES)),
        ("M3b", StateGrid(range_edges=RANGE_EDGES, incidence_edges=INCIDENCE_EDGES)),
    ):
        out[name] = base_model(fit_binned_histogram(samples, grid, edges=edges, z_max=z_max))
    return out


def fine_grid(samples: StateSamples, labels: int = 1) -> StateGrid:
    """The fine state grid of the learned models: 0.5 m ranges to the farthest nominal range, 5 deg incidences."""
    far = float(np.nanmax(samples.nominal[samples.met])) if np.any(samples.met) else 10.0
    return StateGrid(
        range_edges=[float(e) for e in np.arange(0.0, far + 0.5, 0.5)] + [1.0e9],
        incidence_edges=[float(e) for e in np.arange(0.0, 90.0 + 1e-9, 5.0)],
        n_labels=labels,
    )


def fit_learned(train: PlanarTrace, z_max: float, family: str) -> tuple[SensorModel, tuple]:
    """P-Reg or NP-Reg: settings chosen on held-out training scans, then refitted on all training scans.

    Returns:
        The model and the chosen setting (bandwidths; P-Reg's escape law; NP-Reg's uniform share and support
        reach).
    """
    fit_part = train.take(train.scan % 2 == 0)
    check = nominal_beams(train.take(train.scan % 2 == 1))

    def held_out(density) -> float:
        return float(-np.mean(check.log_likelihood(base_model(density))))

    samples = samples_of(train)
    if family == "p_reg":
        _, table = fit_p_reg(samples_of(fit_part), held_out, z_max=z_max)
        h_r, h_d, escape, _ = min(table, key=lambda row: row[-1])
        density, _ = fit_p_reg(
            samples, lambda d: 0.0, h_ranges=(h_r,), h_incidences=(h_d,), escapes=(escape,), z_max=z_max
        )
        setting: tuple = (h_r, h_d, escape)
    else:
        grid = fine_grid(samples)
        _, table = fit_np_reg(samples_of(fit_part), grid, held_out, z_max=z_max)
        h_r, h_i, u, reach, h_null, _ = min(table, key=lambda row: row[-1])
        density, _ = fit_np_reg(
            samples,
            grid,
            lambda d: 0.0,
            h_ranges=(h_r,),
            h_incidences=(h_i,),
            uniforms=(u,),
            reaches=(reach,),
            h_nulls=(h_null,),
            z_max=z_max,
        )
        setting = (h_r, h_i, u, reach, h_null)
    return base_model(density), setting
