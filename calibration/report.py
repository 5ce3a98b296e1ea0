"""Outputs of a calibration run: the calibrated scene (XML + PLY), loss curves (PNG) and change tables."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from xml.sax.saxutils import quoteattr

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mi_lidar.calibration.fit import FitResult  # noqa: E402
from mi_lidar.core.elements import ELLIPSOID_STRIDE, ordered_shapes  # noqa: E402
from mi_lidar.core.errors import CalibrationError  # noqa: E402
from mi_lidar.core.patterns import get_pattern  # noqa: E402
from mi_lidar.scene.dicts import EllipsoidElements, MeshElements, save_scene  # noqa: E402
from mi_lidar.scene.loading import scene_lidar_sensor  # noqa: E402


def element_sets(table, scene) -> dict:
    """``{shape id: MeshElements | EllipsoidElements}`` of a (fitted) :class:`~mi_lidar.core.elements.ElementTable`.

    Raises:
        CalibrationError: a shape is neither a triangle mesh nor an ellipsoid set.
    """
    p_hit, sigma, label = (np.asarray(getattr(table, f)) for f in ("p_hit", "range_sigma", "label"))
    vertices = np.asarray(table.vertex_positions).reshape(-1, 3)
    faces = np.asarray(table.face_vertices).reshape(-1, 3)
    data = np.asarray(table.ellipsoid_data).reshape(-1, ELLIPSOID_STRIDE)
    extent = np.asarray(table.ellipsoid_extent)
    e_index = np.asarray(table.ellipsoid_index)
    sets, offset = {}, 0
    for k, (shape_id, count) in enumerate(zip(table.shape_ids, table.element_counts)):
        sl = slice(offset, offset + count)
        offset += count
        if table.shape_kinds[k] == "ellipsoids":
            e = e_index[sl]
            sets[shape_id] = EllipsoidElements(
                centers=data[e, 0:3],
                scales=data[e, 3:6],
                quaternions=data[e, 6:10],
                p_hit=p_hit[sl],
                label=label[sl],
                extent=float(extent[e[0]]),
            )
        elif table.vertex_offset[k] >= 0:
            first = table.vertex_offset[k]
            mesh_sigma = sigma[sl]
            sets[shape_id] = MeshElements(
                vertices=vertices[first : first + table.vertex_counts[k]],
                faces=faces[sl] - first,
                p_hit=p_hit[sl],
                label=label[sl],
                range_sigma=None if np.all(np.isnan(mesh_sigma)) else np.nan_to_num(mesh_sigma, nan=0.0),
            )
        else:
            raise CalibrationError(
                f"shape {shape_id!r} is an analytic {type(ordered_shapes(scene)[k]).__name__}; calibrated scenes are "
                "written as meshes and ellipsoid sets: convert it to a triangle mesh (e.g. a PLY) first"
            )
    return sets


def sensor_xml(scene, model) -> str:
    """The ``lidar`` sensor (from ``scene``) and ``lidar_integrator`` (with ``model``'s effects) as XML."""
    lines = []
    sensor = scene_lidar_sensor(scene)
    if sensor is not None:
        pattern = sensor.pattern
        matrix = " ".join(f"{v:.9g}" for v in np.asarray(sensor.to_world_matrix).ravel())
        lines += [
            '    <sensor type="lidar" id="lidar">',
            f'        <string name="pattern" value={quoteattr(pattern.name)}/>',
        ]
        if get_pattern(pattern.name).shape != pattern.shape:
            lines.append(f'        <integer name="firings" value="{pattern.shape[1]}"/>')
        lines += [
            f'        <float name="{k}" value="{getattr(model, k):.9g}"/>'
            for k in ("min_range", "max_range", "range_sigma")
        ]
        lines += [f'        <transform name="to_world"><matrix value="{matrix}"/></transform>', "    </sensor>"]
    effects = ", ".join(e.describe() for e in model.effects)
    lines += [
        '    <integrator type="lidar_integrator" id="integrator">',
        f'        <integer name="max_segments" value="{model.max_segments}"/>',
    ]
    if effects:
        lines.append(f'        <string name="effects" value={quoteattr(effects)}/>')
    lines.append("    </integrator>")
    return "\n".join(lines)


def save_calibrated_scene(path, result: FitResult, scene) -> Path:
    """Write the fitted scene as XML plus PLY assets (``<stem>_assets/``), with sensor and effects."""
    return save_scene(path, element_sets(result.table, scene), extra_xml=sensor_xml(scene, result.model))


def loss_png(path, result: FitResult, title: str = "calibration") -> Path:
    """Training loss per step and held-out loss per evaluation (nats per ray) as a PNG."""
    history = np.asarray(result.history, float)
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    train = history[1:]
    ax.plot(train[:, 0], train[:, 1], color="0.6", lw=1, label="training mini-batch")
    held = history[np.isfinite(history[:, 2])]
    ax.plot(held[:, 0], held[:, 2], "o-", color="tab:blue", ms=4, label="held-out")
    ax.axhline(
        result.counting_nll, color="tab:orange", ls="--", lw=1, label=f"counting start ({result.counting_nll:.4f})"
    )
    ax.axhline(result.initial_nll, color="tab:red", ls=":", lw=1, label=f"initial ({result.initial_nll:.4f})")
    ax.set_xlabel("Adam step")
    ax.set_ylabel("negative log-likelihood (nats / ray)")
    ax.set_title(title)
    values = np.r_[held[:, 2], train[:, 1], result.counting_nll, result.initial_nll]
    lo, hi = values.min(), values.max()
    pad = 0.1 * max(hi - lo, 1e-3)
    ax.set_ylim(lo - pad, hi + pad)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def change_rows(result: FitResult, units: dict) -> list[dict]:
    """One row per fitted parameter: size, unit, mean before/after, mean and max absolute change."""
    rows = []
    for name in result.names:
        before, after = np.asarray(result.initial[name], float), np.asarray(result.fitted[name], float)
        change = np.abs(after - before)
        rows.append(
            {
                "parameter": name,
                "values": before.size,
                "unit": units[name],
                "mean_before": float(before.mean()),
                "mean_after": float(after.mean()),
                "mean_abs_change": float(change.mean()),
                "max_abs_change": float(change.max()),
            }
        )
    return rows


def write_report(out, result: FitResult, scene, units: dict, title: str) -> dict[str, Path]:
    """Write ``scene.xml`` (+ assets), ``loss.png``, ``changes.csv``, ``history.csv``, ``parameters.npz`` and
    ``report.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "scene": save_calibrated_scene(out / "scene.xml", result, scene),
        "loss": loss_png(out / "loss.png", result, title),
    }
    rows = change_rows(result, units)
    with open(out / "changes.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    files["changes"] = out / "changes.csv"
    with open(out / "history.csv", "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(["step", "train_nll", "held_out_nll"])
        writer.writerows(result.history)
    files["history"] = out / "history.csv"
    np.savez(
        out / "parameters.npz",
        **{f"initial/{k}": v for k, v in result.initial.items()},
        **{f"fitted/{k}": v for k, v in result.fitted.items()},
    )
    files["parameters"] = out / "parameters.npz"
    summary = {
        "parameters": result.names,
        "steps_run": result.steps_run,
        "stopped_early": result.stopped_early,
        "held_out_nll": {"initial": result.initial_nll, "counting": result.counting_nll, "fitted": result.fitted_nll},
        "effects": [e.describe() for e in result.model.effects],
    }
    (out / "report.json").write_text(json.dumps(summary, indent=1))
    files["report"] = out / "report.json"
    return files
