"""Intensity on real data: reflectivities and the intensity curve fitted to one frame, scored on held-out columns.

Protocol (the Ouster path's columns, :mod:`mi_lidar.loop.real_ouster`): the scene is the range-image
mesh of columns ``0 mod 4``, each face's reflectivity starting from its three vertices' measured
intensity over the model's gain; the intensity model (per-beam gain, incidence exponent, near-field
range, noise) and every face's reflectivity are fitted on columns ``2 mod 4``
(:func:`mi_lidar.calibration.intensity.fit_intensity`); the odd columns are held out. On them:

* **correlation**: Pearson's r between the measured intensity of each return and the model's
  expected intensity of the face its ray meets first;
* **NLL**: the intensity's negative log-likelihood given the range (nats per return, one-unit bins):
  the joint range-and-intensity mixture minus the range-only one, on the returns whose range the
  mesh explains (scored above the floor), from the mixture before the floor;
* **baseline**: a constant per beam, the mean and standard deviation of the beam's calibration
  intensities (Gaussian, the same bins).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.calibration.intensity import fit_intensity
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.intensity import IntensityModel
from mi_lidar.core.likelihood import LOG_FLOOR, mixture_log_likelihood
from mi_lidar.core.log import Log
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.trace import next_intersection
from mi_lidar.loop.real_ouster import MESH_EVERY, range_image_mesh
from mi_lidar.scene.dicts import MeshElements, scene_dict


@dataclass
class IntensityScores:
    """Held-out scores of the fitted intensity model and of the constant-per-beam baseline.

    Attributes:
        attribute: the scored log attribute (``reflectivity``, ``signal``, ``intensity``).
        n_test: held-out returns scored.
        correlation, baseline_correlation: Pearson's r of predicted and measured intensities.
        nll, baseline_nll: intensity NLL per held-out return (nats, one-unit bins).
        model: the fitted intensity model (``describe()`` gives its values).
        measured, predicted, baseline: (n_test,) intensities of the held-out returns.
    """

    attribute: str
    n_test: int
    correlation: float
    baseline_correlation: float
    nll: float
    baseline_nll: float
    model: IntensityModel
    measured: np.ndarray
    predicted: np.ndarray
    baseline: np.ndarray

    def summary(self) -> str:
        return (
            f"{self.attribute}: {self.n_test} held-out returns; model r = {self.correlation:.3f}, "
            f"NLL {self.nll:.3f} nats/return; constant per beam r = {self.baseline_correlation:.3f}, "
            f"NLL {self.baseline_nll:.3f}"
        )


def _raw_log_likelihood(problem: Problem, model: SensorModel) -> np.ndarray:
    """(N,) mixture log-likelihood of the problem's rays before the floor (the intensity's cost is then exact)."""
    problem.trace(model)
    with dr.suspend_grad():
        return np.concatenate(
            [
                np.asarray(mixture_log_likelihood(problem.table, model, c.rays, c.rounds, c.z, c.hit, c.intensity))
                for c in problem.chunks
            ]
        )


def _first_face_intensity(scene, table: ElementTable, model: SensorModel, rays: LogRays, index) -> np.ndarray:
    """Expected intensity of the first face each ray of ``index`` meets (NaN where it meets none)."""
    batch, _, _ = rays.batch(index)
    si, valid, element = next_intersection(scene, table, batch.origin, batch.origin, batch.direction, model.max_range)
    seg = table.traced_segment(si, valid, element, batch.origin, batch.direction, model.range_sigma)
    return np.where(np.asarray(valid), np.asarray(model.intensity.expected(seg, batch)), np.nan)


def intensity_experiment(log: Log, attribute: str = "reflectivity", law: str = "reflectivity", steps: int = 300):
    """Fit and score intensities of a one-scan log with a destaggered image (see the module docstring).

    Args:
        log: the one-scan log (rows are beams, columns azimuth) with attribute ``attribute``.
        attribute: the intensity to model (Ouster ``reflectivity`` or ``signal``, Velodyne ``intensity``).
        law: the intensity law (``reflectivity``: range-compensated; ``signal``: raw).
        steps: Adam steps.

    Returns:
        The :class:`IntensityScores`.
    """
    value = np.where(log.hit, log.attributes[attribute].astype(np.float64), np.nan)
    n_beams, w = log.shape[1], log.shape[2]
    column = np.arange(w)
    mesh_columns = column[column % MESH_EVERY == 0]
    mesh = range_image_mesh(log, mesh_columns)
    intensity = IntensityModel(law=law, gain=100.0, max_value=float(np.nanmax(value)))
    model = SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4, intensity=intensity.widen(n_beams, 1))

    # ---------------- Starting reflectivity: the vertices' intensities over the gain ----------------
    vertex_value = np.nan_to_num(value[0][:, mesh_columns].ravel(), nan=0.0)
    seed = np.clip(vertex_value[mesh.faces].mean(axis=1) / 100.0, 1e-3, 100.0)
    if law == "signal":
        r = np.nan_to_num(log.ranges[0][:, mesh_columns].ravel())[mesh.faces].mean(axis=1)
        seed = np.clip(seed * (r / 10.0) ** 2, 1e-3, 100.0)
    mesh = MeshElements(mesh.vertices, mesh.faces, mesh.p_hit, mesh.label, reflectivity=seed)
    scene = mi.load_dict(scene_dict({"map": mesh}))
    table = ElementTable.from_scene(scene)
    rays = LogRays.from_log(log, intensity=attribute)
    calibration = np.flatnonzero(rays.column % MESH_EVERY == MESH_EVERY // 2)
    test = np.flatnonzero((rays.column % 2 == 1) & rays.hit)

    fit = fit_intensity(model, Problem.build(scene, rays, calibration, table), steps=steps)
    table = table.replaced(reflectivity=mi.Float(fit.reflectivity.astype(np.float32)))

    # ---------------- Held-out scores ----------------
    joint = Problem.build(scene, rays, test, table)
    ranges_only = Problem.build(scene, LogRays.from_log(log), test, table)
    explained = ranges_only.log_likelihood(model) > LOG_FLOOR + 1.0
    intensity_ll = (_raw_log_likelihood(joint, model) - _raw_log_likelihood(ranges_only, model))[explained]
    measured = rays.intensity[test].astype(np.float64)
    predicted = _first_face_intensity(scene, table, model, rays, test)
    beam = rays.beam
    calib_hits = calibration[rays.hit[calibration]]
    mean = np.array([np.mean(rays.intensity[calib_hits][beam[calib_hits] == b]) for b in range(n_beams)])
    sd = np.array([np.std(rays.intensity[calib_hits][beam[calib_hits] == b]) + 0.5 for b in range(n_beams)])
    baseline = mean[beam[test]]
    baseline_ll = -0.5 * ((measured - baseline) / sd[beam[test]]) ** 2 - np.log(sd[beam[test]] * np.sqrt(2 * np.pi))
    known = np.isfinite(predicted)
    return IntensityScores(
        attribute=attribute,
        n_test=int(test.size),
        correlation=float(np.corrcoef(measured[known], predicted[known])[0, 1]),
        baseline_correlation=float(np.corrcoef(measured, baseline)[0, 1]),
        nll=float(-np.mean(intensity_ll)),
        baseline_nll=float(-np.mean(baseline_ll[explained])),
        model=model.intensity,
        measured=measured,
        predicted=predicted,
        baseline=baseline,
    )


def intensity_figure(scores: list[IntensityScores], path: str | Path) -> Path:
    """Measured against predicted held-out intensities (model and baseline) per scored attribute, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_lidar.core.atomic import atomic_path

    fig, axes = plt.subplots(1, len(scores), figsize=(5.5 * len(scores), 5), squeeze=False)
    for ax, s in zip(axes[0], scores):
        top = float(np.nanpercentile(s.measured, 99.5))
        for values, alpha, colour, label in (
            (s.baseline, 0.25, "0.6", f"constant per beam (r={s.baseline_correlation:.2f}, NLL {s.baseline_nll:.2f})"),
            (s.predicted, 0.35, "C0", f"fitted model (r={s.correlation:.2f}, NLL {s.nll:.2f})"),
        ):
            ax.scatter(s.measured, values, s=2, alpha=alpha, color=colour, label=label)
        ax.plot([0, top], [0, top], color="k", lw=0.8)
        ax.set(
            xlim=(0, top),
            ylim=(0, top),
            xlabel=f"measured {s.attribute}",
            ylabel="predicted",
            title=f"held-out columns: {s.attribute}",
        )
        ax.legend(loc="upper left", fontsize=8, markerscale=4)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
