"""Outputs of a calibration run: the calibrated scene (XML + PLY), loss curves (PNG) and change tables."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from xml.sax.saxutils import quoteattr

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

from mi_lidar.calibration.result import FitResult  # noqa: E402
from mi_lidar.core.atomic import atomic_path, atomic_write, atomic_write_text, staged_scene  # noqa: E402
from mi_lidar.core.errors import CalibrationError, PatternError  # noqa: E402
from mi_lidar.core.patterns import get_pattern, to_table  # noqa: E402
from mi_lidar.core.scene_shapes import ELLIPSOID_STRIDE, ordered_shapes  # noqa: E402
from mi_lidar.core.strict_json import write_json  # noqa: E402
from mi_lidar.io.markdown import effects_text, markdown_to_html, plain, spread, table_cell, words  # noqa: E402
from mi_lidar.scene.dicts import AnalyticElements, EllipsoidElements, MeshElements, save_scene  # noqa: E402
from mi_lidar.scene.files import ANALYTIC_SHAPES  # noqa: E402
from mi_lidar.scene.loading import scene_lidar_sensor  # noqa: E402


def element_sets(table, scene) -> dict:
    """``{shape id: MeshElements | EllipsoidElements}`` of a (fitted) :class:`~mi_lidar.core.elements.ElementTable`.

    Raises:
        CalibrationError: a shape cannot be written (see :func:`surface_elements`).
    """
    p_hit, sigma, label = (np.asarray(getattr(table, f)) for f in ("p_hit", "range_sigma", "label"))
    vertices = np.asarray(table.vertex_positions).reshape(-1, 3)
    faces = np.asarray(table.face_vertices).reshape(-1, 3)
    data = np.asarray(table.ellipsoid_data).reshape(-1, ELLIPSOID_STRIDE)
    extent = np.asarray(table.ellipsoid_extent)
    e_index = np.asarray(table.ellipsoid_index)
    shapes = ordered_shapes(scene)
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
            sets[shape_id] = surface_elements(shapes[k], p_hit[sl], sigma[sl], label[sl])
    return sets


def surface_elements(shape, p_hit: np.ndarray, sigma: np.ndarray, label: np.ndarray):
    """The element set of an analytic shape: its own triangles (rectangles) or the shape itself (one element).

    Args:
        shape: the Mitsuba shape.
        p_hit, sigma, label: (count,) per-element values of the shape; sigma NaN = sensor default.

    Raises:
        CalibrationError: a shape that is neither a triangle mesh nor one of
            :data:`~mi_lidar.scene.files.ANALYTIC_SHAPES` (e.g. a curve).
    """
    if isinstance(shape, mi.Mesh):  # a rectangle: two triangles Mitsuba keeps in world space
        return MeshElements(
            vertices=np.asarray(shape.vertex_positions_buffer()).reshape(-1, 3),
            faces=np.asarray(shape.faces_buffer()).reshape(-1, 3),
            p_hit=p_hit,
            label=label,
            range_sigma=None if np.all(np.isnan(sigma)) else np.nan_to_num(sigma, nan=0.0),
        )
    plugin = shape.class_name().lower()
    if plugin not in ANALYTIC_SHAPES or p_hit.size != 1:
        raise CalibrationError(
            f"shape {shape.id()!r} is a {shape.class_name()} with {p_hit.size} elements; calibrated scenes hold "
            f"meshes, ellipsoid sets and the one-element shapes {', '.join(ANALYTIC_SHAPES)}: convert it to a "
            "triangle mesh (e.g. a PLY) first"
        )
    return AnalyticElements(
        plugin=plugin,
        to_world=np.asarray(mi.traverse(shape)["to_world"].matrix, np.float64).reshape(4, 4),
        p_hit=float(p_hit[0]),
        label=int(label[0]),
        range_sigma=None if np.isnan(sigma[0]) else float(sigma[0]),
    )


def pattern_xml(pattern, assets: Path) -> list[str]:
    """The ``pattern`` (and ``firings``) properties of a sensor firing ``pattern``.

    A pattern of the catalog is written by name; any other (a user's table, a log's own rays) is
    written as a table ``<assets>/pattern.npy`` next to the scene (its period is inferred when it
    is read back, see :func:`~mi_lidar.core.patterns.from_table`).
    """
    try:
        preset = get_pattern(pattern.name)
    except PatternError:
        preset = None
    if preset is None or preset.shape[0] != pattern.shape[0]:
        with atomic_path(assets / "pattern.npy") as tmp:
            to_table(pattern, tmp)
        return [f'        <string name="pattern" value={quoteattr(f"{assets.name}/pattern.npy")}/>']
    lines = [f'        <string name="pattern" value={quoteattr(pattern.name)}/>']
    if preset.shape != pattern.shape:
        lines.append(f'        <integer name="firings" value="{pattern.shape[1]}"/>')
    return lines


def sensor_xml(scene, model, assets: Path, pattern=None) -> str:
    """The ``lidar`` sensor and ``lidar_integrator`` (with ``model``'s effects) as XML.

    Args:
        scene: the loaded scene (its sensor's pose and pattern).
        model: the fitted sensor model.
        assets: folder of the scene's assets (a pattern table is written there when needed).
        pattern: the log's firing pattern, when it replaces the scene sensor's.
    """
    lines = []
    sensor = scene_lidar_sensor(scene)
    if sensor is not None or pattern is not None:
        pose = np.eye(4) if sensor is None else sensor.to_world_matrix
        matrix = " ".join(f"{v:.9g}" for v in np.asarray(pose).ravel())
        lines.append('    <sensor type="lidar" id="lidar">')
        lines += pattern_xml(pattern or sensor.pattern, assets)
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


def save_calibrated_scene(path, result: FitResult, scene, pattern=None) -> Path:
    """Write the fitted scene as XML plus PLY assets (``<stem>_assets/``), with sensor and effects.

    ``pattern`` (the log's firing pattern) replaces the scene sensor's when given. The XML and its assets
    appear together or not at all (:func:`~mi_lidar.core.atomic.staged_scene`): a write that fails midway
    keeps a previous scene and its assets as they were.
    """
    path = Path(path)
    sets = element_sets(result.table, scene)
    with staged_scene(path) as staged:
        assets = staged.with_name(f"{path.stem}_assets")
        save_scene(staged, sets, extra_xml=sensor_xml(scene, result.model, assets, pattern))
    return path


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
    if result.shared:
        label = f"per-beam fit from the shared start ({result.shared_nll:.4f})"
        ax.axvline(result.shared_steps, color="0.3", ls="-.", lw=1, label=label)
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
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return Path(path)


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


def write_report(out, result: FitResult, scene, units: dict, title: str, pattern=None) -> dict[str, Path]:
    """Write ``scene.xml`` (+ assets), ``loss.png``, ``changes.csv``, ``history.csv``, ``parameters.npz``,
    ``report.json`` and ``report.html``, each atomically; ``pattern`` (the log's) replaces the scene
    sensor's in ``scene.xml``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {
        "scene": save_calibrated_scene(out / "scene.xml", result, scene, pattern),
        "loss": loss_png(out / "loss.png", result, title),
    }
    rows = change_rows(result, units)
    files["changes"] = _write_csv(out / "changes.csv", list(rows[0]), [list(row.values()) for row in rows])
    files["history"] = _write_csv(out / "history.csv", ["step", "train_nll", "held_out_nll"], result.history)
    arrays = {f"initial/{k}": v for k, v in result.initial.items()} | {
        f"fitted/{k}": v for k, v in result.fitted.items()
    }
    files["parameters"] = atomic_write(out / "parameters.npz", lambda stream: np.savez(stream, **arrays))
    summary = {
        "parameters": result.names,
        "steps_run": result.steps_run,
        "stopped_early": result.stopped_early,
        "held_out_nll": {
            "initial": result.initial_nll,
            "counting": result.counting_nll,
            **({"shared_start": result.shared_nll} if result.shared else {}),
            "fitted": result.fitted_nll,
        },
        "shared_start": result.shared,
        "effects": [e.describe() for e in result.model.effects],
        "held_out_samples": result.samples,
        "warnings": result.warnings,
    }
    files["report"] = write_json(out / "report.json", summary)
    page = markdown_to_html(
        calibration_markdown(summary, rows, title, result.fitted, effects_text(result.model.effects)), title
    )
    files["html"] = atomic_write_text(out / "report.html", page)
    return files


SHARED_KEPT = (
    "The fit beam by beam did not score the held-out rays better than the shared start: the values of the shared "
    "start are kept (one value on every beam)."
)  # said where a user otherwise sees 180 equal per-beam values and wonders why
CHANGE_HEADERS = {"mean_abs_change": "mean |change|", "max_abs_change": "max |change|"}  # words() for the rest


def calibration_markdown(
    summary: dict, rows: list[dict], title: str, fitted: dict | None = None, effects: str = "none"
) -> str:
    """The calibration report page: held-out NLL before and after, the parameters' changes, the loss trace.

    Args:
        summary: ``report.json``'s content.
        rows: :func:`change_rows`, a table row each (its columns in words).
        title: the page's title.
        fitted: ``{parameter: fitted values}``: a parameter of more than one value gets a line of their spread
            (:func:`~mi_lidar.io.markdown.spread`; every value is in ``parameters.npz``).
        effects: the calibrated scene's effects as text (:func:`~mi_lidar.io.markdown.effects_text`).
    """
    nll = summary["held_out_nll"]
    many = [row for row in rows if row["values"] > 1 and row["parameter"] in (fitted or {})]
    lines = [
        f"# {title}",
        "",
        *(f"**Warning:** {w}.\n" for w in summary.get("warnings", [])),
        f"Held-out NLL (nats/ray): initial **{nll['initial']:.4f}**, counting start {nll['counting']:.4f}, "
        + (f"shared start {nll['shared_start']:.4f}, " if "shared_start" in nll else "")
        + f"fitted **{nll['fitted']:.4f}**; {summary['steps_run']} Adam steps"
        + (" (stopped early: the held-out loss stopped falling)." if summary["stopped_early"] else "."),
        "",
        *([SHARED_KEPT, ""] if nll.get("shared_start") == nll["fitted"] else []),
        *_samples_table(summary.get("held_out_samples", {})),
        "## Parameters",
        "",
        "| " + " | ".join(table_cell(CHANGE_HEADERS.get(k, words(k))) for k in rows[0]) + " |",
        "|" + "---|" * len(rows[0]),
        *(
            "| " + " | ".join(table_cell(f"{v:,}" if isinstance(v, int) else plain(v)) for v in row.values()) + " |"
            for row in rows
        ),
        "",
        *(f"Fitted `{row['parameter']}` ({row['unit']}): {spread(fitted[row['parameter']])}." for row in many),
        *(
            ["", "Every value before and after: `parameters.npz` (`initial/<parameter>`, `fitted/<parameter>`).", ""]
            if many
            else []
        ),
        "## Training and held-out loss",
        "",
        "![loss](loss.png)",
    ]
    if summary["effects"]:
        lines += ["", "## Effects in the calibrated scene", "", effects + " (every value: `scene.xml`)."]
    return "\n".join(lines) + "\n"


SAMPLE_COLUMNS = (
    ("nll", "NLL (nats/ray)"),
    ("range_error_median", "median abs range error (m)"),
    ("range_error_p90", "p90 abs range error (m)"),
    ("f1", "hit/miss F1"),
    ("histogram_l1", "histogram L1 (m)"),
    ("chamfer", "Chamfer (m)"),
)


def _samples_table(samples: dict) -> list[str]:
    """Markdown lines: the held-out NLL beside the realism of the scans the initial and fitted models sample."""
    if not samples:
        return []
    return [
        "## Samples beside the likelihood (held-out rays)",
        "",
        "One scan sampled at the held-out rays by each model, against the measured one: a fit that wins the "
        "NLL by spreading its mass shows here.",
        "",
        "| model | " + " | ".join(title for _, title in SAMPLE_COLUMNS) + " |",
        "|" + "---|" * (len(SAMPLE_COLUMNS) + 1),
        *(
            f"| {name} | " + " | ".join(f"{row.get(key, float('nan')):.4g}" for key, _ in SAMPLE_COLUMNS) + " |"
            for name, row in samples.items()
        ),
        "",
    ]


def _write_csv(path: Path, header: list, rows) -> Path:
    """A CSV file with ``header`` and ``rows``, written atomically; a NaN (a value not evaluated) is an empty cell."""
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(header)
    writer.writerows(["" if isinstance(v, float) and np.isnan(v) else v for v in row] for row in rows)
    return atomic_write_text(path, text.getvalue())
