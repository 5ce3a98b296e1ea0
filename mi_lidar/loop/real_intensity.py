"""Intensity on real data: reflectivities and the intensity curve calibrated on one frame, scored on held-out columns.

Protocol (the Ouster path's columns, :mod:`mi_lidar.loop.real_ouster`; any one-scan log with a
destaggered image: rows are beams, columns azimuth):

* **scene**: the range-image mesh of columns ``0 mod 4``; each face's starting reflectivity is the
  mean of its three vertices' *apparent* reflectivities (their measured intensity through the
  inverted law, :meth:`~mi_lidar.core.intensity.IntensityModel.apparent_reflectivity`);
* **calibration**: columns ``2 mod 4``, by :func:`~mi_lidar.calibration.intensity.calibrate_intensity`:
  the intensity curve and noise with the starting reflectivities, then every face's reflectivity
  under a log-normal prior about its start;
* **check**: columns ``1 mod 4`` choose the prior's width (they meet the faces the calibration
  columns meet, one column away, as the test columns do);
* **test**: the returns of columns ``3 mod 4`` whose range the first face their ray meets explains
  (the range likelihood scores them above the floor + 1 nat; the check columns' NLL counts the
  same returns). For an opaque mesh the joint likelihood of such a return factorises as
  ``f_1(z) g_1(I)`` at the first face, so the intensity's NLL given the range is ``-log g_1(I)``
  (nats per return, one-unit bins); the correlation is Pearson's r between the measured intensity
  and the first face's expected one. The report also scores every return whose ray meets a face
  (a return from behind a face across a depth jump is then predicted from the wrong surface);
* **baselines** (same returns): a constant per beam with the model's own noise law (floor, relative
  part, outliers; fitted on the calibration columns by the same fitter), and the mean and standard
  deviation of the beam's calibration intensities as a Gaussian.

Why the shrinkage: the mesh has more faces (11,337 on the Ouster frame) than the calibration
columns have returns (6,804), so free per-face reflectivities fitted with the noise reproduce every
calibration intensity, the noise collapses to its bounds (floor 0.29, relative 0.001) and
held-out returns cost 7.4 nats each (REFLECTIVITY, every return meeting a face; the constant per
beam: 4.1). With the noise fitted where the reflectivities are not, and the reflectivities shrunk
toward their vertices' values, the model wins on both scores.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.calibration.intensity import calibrate_intensity, fit_intensity
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.intensity import IntensityModel
from mi_lidar.core.likelihood import LOG_FLOOR
from mi_lidar.core.log import Log
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.intensity_residuals import first_element_intensity
from mi_lidar.loop.real_ouster import MESH_EVERY, range_image_mesh
from mi_lidar.scene.dicts import MeshElements, scene_dict

CHECK_COLUMN, TEST_COLUMN = 1, 3  # columns 1 mod 4 choose the prior width and noise, 3 mod 4 test


PREDICTORS = {"model": "calibrated model", "constant": "constant per beam", "gaussian": "constant per beam, Gaussian"}
SUBSETS = {
    "explained": "returns whose range the first face explains",
    "met": "all returns whose ray meets a face",
}


@dataclass
class IntensityScores:
    """Held-out intensities of the test returns whose ray meets a face, as the model and the baselines see them.

    Attributes:
        sensor: the log's sensor name (``ouster:OS-1-32-G``).
        attribute: the scored log attribute (``reflectivity``, ``signal``, ``intensity``).
        prior_sigma: the chosen width of the reflectivity prior (ln reflectivity).
        selection: ``{prior width: check NLL}`` (nats per ray of the check columns ``1 mod 4``).
        model: the calibrated intensity model (``describe()`` gives its values).
        measured: (N,) measured intensities.
        expected: ``{predictor: (N,) expected intensity}`` for the model and the constant per beam.
        log_g: ``{predictor: (N,) log density of the measured intensity}`` (one-unit bins) for the
            model, the constant per beam with the model's noise law, and the Gaussian constant.
        explained: (N,) the first face explains the return's range (scored above the floor + 1 nat
            by the range likelihood): the intensity scores of :attr:`SUBSETS` ``explained``.
        nominal, cos_incidence, beam: (N,) range (m), incidence cosine and beam of the first face.
    """

    sensor: str
    attribute: str
    prior_sigma: float
    selection: dict
    model: IntensityModel
    measured: np.ndarray
    expected: dict
    log_g: dict
    explained: np.ndarray
    nominal: np.ndarray
    cos_incidence: np.ndarray
    beam: np.ndarray

    def score(self, predictor: str = "model", subset: str = "explained") -> dict:
        """``{"returns", "correlation", "nll"}`` of ``predictor`` on ``subset`` (Pearson's r; nats per return).

        The Gaussian constant's correlation is the constant's (same expected values).
        """
        keep = self.explained if subset == "explained" else np.ones(self.measured.size, bool)
        expected = self.expected["constant" if predictor == "gaussian" else predictor][keep]
        return {
            "returns": int(keep.sum()),
            "correlation": float(np.corrcoef(self.measured[keep], expected)[0, 1]),
            "nll": float(-np.mean(self.log_g[predictor][keep])),
        }

    def rows(self) -> list[dict]:
        """One row per subset and predictor (the report's table)."""
        return [
            {"subset": SUBSETS[subset], "predictor": PREDICTORS[predictor], **self.score(predictor, subset)}
            for subset in SUBSETS
            for predictor in PREDICTORS
        ]

    def summary(self) -> str:
        model, constant, gaussian = self.score("model"), self.score("constant"), self.score("gaussian")
        return (
            f"{self.sensor} {self.attribute}: {model['returns']} held-out returns; model r = "
            f"{model['correlation']:.3f}, NLL {model['nll']:.3f} nats/return; constant per beam r = "
            f"{constant['correlation']:.3f}, NLL {constant['nll']:.3f} (Gaussian: {gaussian['nll']:.3f}); "
            f"reflectivity prior width {self.prior_sigma:g}"
        )


def seed_reflectivity(log: Log, mesh: MeshElements, columns: np.ndarray, attribute: str, model: IntensityModel):
    """Starting reflectivity of each face: the mean apparent reflectivity of its three vertices.

    Each vertex is a measured return (row = beam) of ``columns``; its intensity goes through the
    inverted law of ``model`` at the vertex's range and beam and the face's incidence.

    Returns:
        (F,) reflectivities.
    """
    n_columns = len(columns)
    rotation = log.poses[0, :3, :3]
    direction = (log.directions[0][:, columns].reshape(-1, 3) @ rotation.T)[mesh.faces]  # (F, 3, 3)
    corners = mesh.vertices[mesh.faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    cos = np.abs(np.einsum("fk,fvk->fv", normal, direction))
    value = log.attributes[attribute][0][:, columns].reshape(-1).astype(np.float64)[mesh.faces]
    nominal = np.nan_to_num(log.ranges[0][:, columns].reshape(-1))[mesh.faces]
    rho = model.apparent_reflectivity(value.ravel(), nominal.ravel(), cos.ravel(), (mesh.faces // n_columns).ravel())
    return rho.reshape(-1, 3).mean(axis=1)


def intensity_experiment(
    log: Log, attribute: str = "reflectivity", law: str = "reflectivity", steps: int = 150, progress=None
) -> IntensityScores:
    """Calibrate and score the intensities of a one-scan log (see the module docstring).

    Args:
        log: the one-scan log (rows are beams, columns azimuth) with attribute ``attribute``.
        attribute: the intensity to model (Ouster ``reflectivity`` or ``signal``, Velodyne ``intensity``).
        law: the intensity law (``reflectivity``: range-compensated; ``signal``: raw).
        steps: Adam steps of each fit.
        progress: optional ``progress(message)``.

    Returns:
        The :class:`IntensityScores`.

    Raises:
        LogFormatError: the log has several scans or no attribute ``attribute``.
    """
    if log.shape[0] != 1:
        raise LogFormatError(f"intensity_experiment: the log has {log.shape[0]} scans; pass one, e.g. log.scan(0)")
    rays = LogRays.from_log(log, intensity=attribute)
    n_beams, w = log.shape[1], log.shape[2]
    column = np.arange(w)
    mesh_columns = column[column % MESH_EVERY == 0]
    calibration = np.flatnonzero(rays.column % MESH_EVERY == MESH_EVERY // 2)
    check = np.flatnonzero(rays.column % MESH_EVERY == CHECK_COLUMN)
    test = np.flatnonzero((rays.column % MESH_EVERY == TEST_COLUMN) & rays.hit)
    top = float(np.nanmax(rays.intensity[calibration]))
    # incidence exponent 0: seeds are the intensities as seen (a Lambertian division by the face's cos
    # inflates the faces across depth jumps, seen edge-on, into bright false faces)
    intensity = IntensityModel(law=law, gain=100.0, incidence_exponent=0.0, max_value=top).widen(n_beams, 1)
    model = SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4, intensity=intensity)

    # ---------------- Scene: the mesh, each face starting from its vertices' apparent reflectivity ----------------
    mesh = range_image_mesh(log, mesh_columns)
    seed = np.clip(seed_reflectivity(log, mesh, mesh_columns, attribute, intensity), 1e-3, 100.0)
    mesh = MeshElements(mesh.vertices, mesh.faces, mesh.p_hit, mesh.label, reflectivity=seed)
    scene = mi.load_dict(scene_dict({"map": mesh}))
    table = ElementTable.from_scene(scene)

    # ---------------- Calibration: curve, then reflectivities with the held-out prior width ----------------
    calibrated = calibrate_intensity(model, scene, table, rays, calibration, check, steps=steps, progress=progress)
    table = table.replaced(reflectivity=mi.Float(calibrated.reflectivity.astype(np.float32)))

    # ---------------- Baselines: a constant per beam (the model's noise law; a Gaussian) ----------------
    hits = calibration[rays.hit[calibration]]
    values = [rays.intensity[hits][rays.beam[hits] == b] for b in range(n_beams)]
    mean = np.array([v.mean() if v.size else np.nan for v in values])
    sd = np.array([v.std() + 0.5 if v.size else np.nan for v in values])
    constant = SensorModel(
        range_sigma=0.01,
        max_range=120.0,
        max_segments=4,
        intensity=IntensityModel(
            gain=np.nan_to_num(mean, nan=1.0), incidence_exponent=0.0, near_range=0.0, max_value=top
        ),
    )
    white = table.replaced(reflectivity=dr.ones(mi.Float, table.n_elements))
    fixed = ("incidence_exponent", "near_range")
    fit_intensity(constant, Problem.build(scene, rays, calibration, white), steps=steps, prior_sigma=0.0, fixed=fixed)

    # ---------------- Held-out scores, on the test returns whose ray meets a face ----------------
    scored = first_element_intensity(scene, table, model, rays, test)
    reference = first_element_intensity(scene, white, constant, rays, test)
    met = scored["met"]
    range_ll = Problem.build(scene, LogRays.from_log(log), test[met], table).log_likelihood(model)
    measured = rays.intensity[test][met].astype(np.float64)
    beam = rays.beam[test][met]
    gaussian = -0.5 * ((measured - mean[beam]) / sd[beam]) ** 2 - np.log(sd[beam] * np.sqrt(2 * np.pi))
    return IntensityScores(
        sensor=str(log.sensor.get("name", "")),
        attribute=attribute,
        prior_sigma=calibrated.prior_sigma,
        selection=calibrated.selection,
        model=model.intensity,
        measured=measured,
        expected={"model": scored["expected"][met], "constant": reference["expected"][met]},
        log_g={"model": scored["log_g"][met], "constant": reference["log_g"][met], "gaussian": gaussian},
        explained=range_ll > LOG_FLOOR + 1.0,
        nominal=scored["nominal"][met],
        cos_incidence=scored["cos_incidence"][met],
        beam=beam,
    )


def intensity_figure(scores: list[IntensityScores], path: str | Path) -> Path:
    """Measured against predicted held-out intensities (model and baseline, log axes) and the prior-width
    choice, one row per scored attribute, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_lidar.core.atomic import atomic_path

    fig, axes = plt.subplots(len(scores), 2, figsize=(11, 4.8 * len(scores)), squeeze=False, width_ratios=(1.4, 1))
    for (ax, choice), s in zip(axes, scores):
        keep = s.explained
        top = float(np.nanmax(s.measured[keep])) + 1.0
        for predictor, alpha, colour in (("constant", 0.25, "0.6"), ("model", 0.3, "C0")):
            score = s.score(predictor)
            label = f"{PREDICTORS[predictor]} (r={score['correlation']:.2f}, NLL {score['nll']:.2f})"
            values = s.expected[predictor][keep] + 1.0
            ax.scatter(s.measured[keep] + 1.0, values, s=2, alpha=alpha, color=colour, label=label, lw=0)
        ax.plot([1, top], [1, top], color="k", lw=0.8)
        ax.set(
            xscale="log",
            yscale="log",
            xlim=(1, top),
            ylim=(1, top),
            xlabel=f"measured {s.attribute} + 1",
            ylabel="predicted + 1",
            title=f"{s.sensor} {s.attribute}, test columns ({int(keep.sum()):,} returns; NLL nats/return)",
        )
        ax.legend(loc="upper left", fontsize=8, markerscale=4)
        widths = list(s.selection)
        position = np.arange(len(widths))
        choice.plot(position, list(s.selection.values()), "o-", color="C1")
        choice.axvline(widths.index(s.prior_sigma), color="k", lw=0.8, ls="--", label="chosen")
        choice.set_xticks(position, [f"{x:g}" if np.isfinite(x) else "free" for x in widths])
        choice.set(
            xlabel="reflectivity prior width (ln units; 0: vertex seeds kept)",
            ylabel="check NLL (nats/ray)",
            title=f"prior width chosen on columns {CHECK_COLUMN} mod {MESH_EVERY}",
        )
        choice.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return path


def write_intensity_report(scores: list[IntensityScores], out: str | Path) -> Path:
    """``report.md``, ``report.html`` and ``intensity.png`` in ``out``: the scores of every channel, the chosen
    prior widths and the calibrated models; returns the HTML page."""
    from mi_lidar.core.atomic import atomic_write_text
    from mi_lidar.io.markdown import markdown_to_html
    from mi_lidar.loop.report import table_cell

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    intensity_figure(scores, out / "intensity.png")
    lines = [
        "# Intensity calibrated on real frames",
        "",
        "Scene: the range-image mesh of columns 0 mod 4, each face starting from its vertices' intensities; "
        "calibration on columns 2 mod 4 (curve and noise, then each face's reflectivity under a log-normal prior "
        "about its start); columns 1 mod 4 choose the prior's width and the noise; test on columns 3 mod 4 "
        "(mi_lidar.loop.real_intensity). Correlation: Pearson's r of measured and expected intensity. NLL: "
        "-log of the measured intensity's density at the first face (nats per return, one-unit bins).",
        "",
        "| channel | returns scored | predictor | returns | r | NLL (nats/return) |",
        "|---|---|---|---|---|---|",
    ]
    for s in scores:
        for row in s.rows():
            lines.append(
                f"| {s.sensor} {s.attribute} | {table_cell(row['subset'])} | {row['predictor']} | {row['returns']} | "
                f"{row['correlation']:.3f} | {row['nll']:.3f} |"
            )
    lines += ["", "![measured against predicted intensities](intensity.png)", ""]
    for s in scores:
        widths = ", ".join(f"{w:g}: {nll:.4f}" for w, nll in s.selection.items())
        lines += [
            f"## {s.sensor} {s.attribute}",
            "",
            f"Chosen reflectivity prior width **{s.prior_sigma:g}** (ln units; check NLL per ray by width: {widths}).",
            "",
            f"Calibrated model: `{s.model.describe()}`",
            "",
        ]
    markdown = "\n".join(lines)
    atomic_write_text(out / "report.md", markdown)
    atomic_write_text(out / "report.html", markdown_to_html(markdown, "mi-lidar: intensity on real frames"))
    return out / "report.html"
