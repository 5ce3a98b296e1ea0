"""Command functions of the hybrid-scene tools (plain functions; the CLI wires them to Typer).

Examples::

    fit_scene("train.npz", "out/train_scene")               # -> [out/train_scene/scene.xml, its assets, previews]
    primitives_extract("train.npz", "library")              # labelled log -> primitive library
    primitives_list("library")                              # table of primitives
    primitives_show("library", "library.png")               # preview PNG
    annotate("test.npz", "test_annotation.json")            # labelled log -> annotation + ground + sensor
    compose("test_annotation.json", "library", "out/test.xml")  # scene + range-image and top-view PNGs

The verbs that write files return every path they wrote, the main file first; the CLI names them all.

Every written scene holds a ``lidar`` sensor and a ``lidar_integrator``: it loads with
:func:`mi_lidar.load_scene`, renders with ``mi.render`` and simulates with :func:`mi_lidar.simulate`.
"""

from __future__ import annotations

import shutil
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import mitsuba as mi
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from mi_lidar.core.atomic import staged_scene
from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.log import Log
from mi_lidar.core.patterns import is_pattern_file
from mi_lidar.hybrid.blocks import SceneSensor, assets_folder, write_scene
from mi_lidar.hybrid.compose import (
    annotation_from_segments,
    annotation_sensor,
    compose_scene,
    load_annotation,
    save_annotation,
)
from mi_lidar.hybrid.fit import FitParams, FitResult, fit_model
from mi_lidar.hybrid.model import HybridModel
from mi_lidar.hybrid.primitives import PrimitiveLibrary, extract_primitives
from mi_lidar.hybrid.segments import segments_from_labels
from mi_lidar.io.dispatch import read_any
from mi_lidar.io.preview import birds_eye_png, range_image_png
from mi_lidar.scene.loading import load_scene
from mi_lidar.scene.simulation import simulate

console = Console(stderr=True)

DEFAULT_PATTERN = "hdl32e"  # composed scenes without a sensor in their annotation
MOUNT_HEIGHT = 1.8  # m, sensor height above the ground for such scenes


@contextmanager
def progress_bar(title: str):
    """A rich progress bar; yields a ``progress(stage, fraction)`` callback for :func:`fit_model`."""
    with Progress(
        TextColumn(f"{title}: [bold]{{task.description}}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("start", total=1.0)
        yield lambda stage, fraction: bar.update(task, description=stage, completed=fraction)


def _fit(log: Log, params: FitParams | None, title: str, ground_only: bool = False) -> FitResult:
    with progress_bar(title) as report:
        return fit_model(log, params, report, ground_only=ground_only)


def _require_labels(log: Log, path) -> None:
    missing = [k for k in ("label", "instance") if k not in log.attributes]
    if missing:
        raise LogFormatError(
            f"{path}: the log has no per-ray {' and '.join(missing)}; primitives and annotations need a labelled log "
            "(a ground-truth label and instance per ray), e.g. `mi-lidar synth-world --out train.npz` (from Python: "
            "mi_lidar.hybrid.true_sensor.render_log)"
        )


def render_previews(xml, poses: np.ndarray | None = None, seed: int = 0, max_scans: int = 20) -> tuple[Path, Path]:
    """Render a written scene with the core and save ``<stem>_range.png`` and ``<stem>_top.png``.

    The range image is ``mi.render`` at the scene's sensor pose; the top view shows the points of
    :func:`mi_lidar.simulate` at up to ``max_scans`` of ``poses`` (default: the sensor pose),
    coloured by height.

    Args:
        xml: scene XML with a ``lidar`` sensor. poses: (S, 4, 4) sensor poses. seed: random seed.
        max_scans: most poses simulated for the top view (evenly picked).

    Returns:
        The two PNG paths.
    """
    xml = Path(xml)
    scene = load_scene(xml)
    image = np.array(mi.render(scene, seed=seed))
    ranges = np.where(image[..., 1] > 0, image[..., 0], np.nan)
    range_png = range_image_png(xml.with_name(f"{xml.stem}_range.png"), ranges, title=f"{xml.name}: mi.render")
    if poses is not None and len(poses) > max_scans:
        poses = poses[np.linspace(0, len(poses) - 1, max_scans).round().astype(int)]
    with progress_bar(f"preview {xml.name}") as report:
        log = simulate(scene, poses=poses, seed=seed, progress=lambda done, total: report("simulate", done / total))
    points = log.points_world()[log.hit]
    top_png = birds_eye_png(
        xml.with_name(f"{xml.stem}_top.png"), points, title=f"{xml.name}: mi_lidar.simulate, {log.n_scans} scans"
    )
    return range_png, top_png


def write_scene_together(model: HybridModel, out_xml: Path, sensor: SceneSensor | None = None, log=None) -> list[Path]:
    """:func:`~mi_lidar.hybrid.blocks.write_scene` of ``model`` at ``out_xml`` by :func:`write_staged`: the XML and
    its assets together or not at all, every file named relative to the XML.

    Returns:
        The paths written: the XML, its PLY assets, then the pattern file when ``log`` is given or the sensor's pattern
        is a file.
    """
    return write_staged(out_xml, lambda folder, stem, s: write_scene(model, folder, stem, s), sensor, log)


def write_staged(out_xml: Path, write, sensor: SceneSensor | None = None, log=None) -> list[Path]:
    """Write a scene at ``out_xml`` with ``write``, the XML and its assets together or not at all
    (:func:`~mi_lidar.core.atomic.staged_scene`): a write that fails midway keeps a previous scene whole.

    The XML names every file relative to itself, so its folder can be moved or shared whole.

    Args:
        out_xml: the scene XML; its assets go to ``<stem>_assets/`` beside it.
        write: ``write(folder, stem, sensor)`` writes ``<folder>/<stem>.xml`` and its assets and returns their paths,
            the XML first (:func:`~mi_lidar.hybrid.blocks.write_scene`).
        sensor: the scene's sensor (None: shapes only); a pattern given as a file (a table or Ouster metadata) is
            copied to ``<stem>_assets/pattern<suffix>``, or
        log: a log whose scan-0 pattern the sensor fires from its first pose, written as ``<stem>_assets/pattern.npy``;
            with ``sensor`` as well, the sensor's other settings (pose, range limits, sigma) are kept.

    Returns:
        The paths written: ``write``'s, then the pattern file when ``log`` is given or the sensor's pattern is a file.
    """
    with staged_scene(out_xml) as staged:
        table = []
        if log is not None:
            table = [assets_folder(staged.parent, out_xml.stem) / "pattern.npy"]
            from_log = SceneSensor.from_log(log, table[0])
            sensor = from_log if sensor is None else replace(sensor, pattern=from_log.pattern)
        elif sensor is not None and is_pattern_file(sensor.pattern):
            table = [assets_folder(staged.parent, out_xml.stem) / f"pattern{Path(sensor.pattern).suffix.lower()}"]
            shutil.copyfile(sensor.pattern, table[0])
        if table:
            sensor = replace(sensor, pattern=f"{table[0].parent.name}/{table[0].name}")
        written = [*write(staged.parent, out_xml.stem, sensor), *table]
    return [out_xml.parent / path.relative_to(staged.parent) for path in written]


def fit_scene(
    log_path, out_dir, params: FitParams | None = None, name: str = "scene", preview: bool = True
) -> list[Path]:
    """Fit a hybrid model to the log at ``log_path`` (or a :class:`Log` read already) and write
    ``<out_dir>/<name>.xml``.

    The scene's sensor fires the log's scan-0 pattern (``<name>_assets/pattern.npy``) from its
    first pose. With ``preview``, ``<name>_range.png`` and ``<name>_top.png`` are rendered.

    Returns:
        The paths written: the XML first, then its PLY assets, the pattern table and the previews.
    """
    log = log_path if isinstance(log_path, Log) else read_any(log_path)
    if log.is_planar:
        console.print(
            f"warning: {log.source or 'the log'} is a planar log (every beam in one plane): a hybrid scene's ground "
            "and vegetation need a 3D scan, so the scene fitted here is a guess outside that plane; `mi-lidar "
            "fit-scene` builds a planar log's wall map instead (mi_lidar.planar.map_scene.fit_map_scene)",
            highlight=False,
            markup=False,
            soft_wrap=True,
        )
    result = _fit(log, params, "fit")
    xml, *shapes, pattern = write_scene_together(result.model, Path(out_dir) / f"{name}.xml", log=log)
    table = Table(title=f"hybrid scene {xml}")
    for col in ("points", "ground points", "triangles", "ellipsoids", "blocks", "triangle p_hit", "seconds"):
        table.add_column(col, justify="right")
    table.add_row(
        f"{len(result.points):,}",
        f"{int(result.is_ground.sum()):,}",
        f"{len(result.model.ground):,}",
        f"{len(result.model.ellipsoids):,}",
        f"{result.model.info['n_blocks']:,}",
        f"{result.model.info['mean_triangle_p_hit']:.2f}",
        f"{sum(result.timings.values()):.1f}",
    )
    console.print(table)
    return [xml, *shapes, pattern, *(render_previews(xml, log.poses) if preview else ())]


def primitives_extract(log_path, library_dir, params: FitParams | None = None) -> PrimitiveLibrary:
    """Fit the labelled log, cut its objects into primitives and add them to ``library_dir``."""
    log = read_any(log_path)
    _require_labels(log, log_path)
    result = _fit(log, params, "extract")
    labels = log.attributes["label"].ravel()[result.ray_index]
    inst = log.attributes["instance"].ravel()[result.ray_index]
    segs = segments_from_labels(result.points, labels, inst)
    library = (
        PrimitiveLibrary.load(library_dir) if (Path(library_dir) / "library.json").is_file() else PrimitiveLibrary()
    )
    library.add(extract_primitives(result.model, result.points, segs, log.poses, source=Path(log_path).stem))
    library.save(library_dir)
    return library


def primitives_table(rows: list[dict], title: str) -> Table:
    """A table of :meth:`PrimitiveLibrary.rows` that keeps to 80 columns: an id longer than its column folds.

    The source's scene and segment are the id's parts (``<scene>_<class>_<segment>``); its returns count
    and its patch flag make the ``points`` column.
    """
    table = Table(
        title=title,
        caption="points: the returns the primitive was fitted to; *: from a cell of a shrub patch",
        header_style="bold",
    )
    table.add_column("id", overflow="fold")
    table.add_column("class", no_wrap=True)
    table.add_column("ellip-\nsoids", justify="right")  # a short header leaves the id its room
    table.add_column("extents (m)", justify="right", no_wrap=True)
    table.add_column("points", justify="right", no_wrap=True)
    for r in rows:
        source = r.get("source") or {}
        points = f"{source['n_points']:,}" if "n_points" in source else "-"
        table.add_row(
            r["id"],
            r["class"],
            str(r["ellipsoids"]),
            "\u00d7".join(f"{x:.2f}" for x in r["extents"]),
            points + ("*" if source.get("patch") else ""),
        )
    return table


def primitives_list(library_dir, out: Console = console) -> list[dict]:
    """Print (on ``out``) and return a summary row per primitive of the library at ``library_dir``."""
    rows = PrimitiveLibrary.load(library_dir).rows()
    out.print(primitives_table(rows, str(library_dir)) if rows else f"{library_dir}: no primitives")
    return rows


def primitives_show(library_dir, out_png, ids: list[str] | None = None, per_class: int = 4) -> Path:
    """Write a preview PNG of primitives (all classes, or ``ids``); return its path."""
    return PrimitiveLibrary.load(library_dir).preview(out_png, per_class=per_class, ids=ids)


def annotate(log_path, out_json, params: FitParams | None = None) -> list[Path]:
    """Annotation of a labelled log: objects from its labels, ground mesh fitted to its ground
    points, and its sensor (pattern, poses, range limits); return the paths written, the JSON first
    (:func:`~mi_lidar.hybrid.compose.save_annotation`)."""
    log = read_any(log_path)
    _require_labels(log, log_path)
    result = _fit(log, params, "annotate", ground_only=True)
    labels = log.attributes["label"].ravel()[result.ray_index]
    inst = log.attributes["instance"].ravel()[result.ray_index]
    objects = annotation_from_segments(result.points, segments_from_labels(result.points, labels, inst), log.poses)
    written = save_annotation(out_json, objects, result.model.ground, log)
    console.print(f"{len(objects):,} objects, {len(result.model.ground):,} ground triangles in {written[0]}")
    return written


def _default_sensor(model: HybridModel) -> tuple[SceneSensor, np.ndarray]:
    """A ``DEFAULT_PATTERN`` sensor MOUNT_HEIGHT above the middle of the scene."""
    pts = model.ground.vertices if len(model.ground) else model.ellipsoids.means
    pose = np.eye(4)
    if len(pts):
        pose[:3, 3] = np.median(pts, axis=0) + [0.0, 0.0, MOUNT_HEIGHT]
    return SceneSensor(DEFAULT_PATTERN, pose, 1.0, 80.0), pose[None]


def compose(annotation, library, out_xml, extent: float = 3.5, preview: bool = True) -> list[Path]:
    """Build the scene of ``annotation`` from the primitive library folder ``library``; write ``out_xml``.

    The sensor is the annotation's (its pattern and first pose), else an ``hdl32e`` 1.8 m above
    the middle of the scene. With ``preview``, ``<stem>_range.png`` and ``<stem>_top.png`` are
    rendered along the annotation's poses.

    Returns:
        The paths written: the XML first, then its PLY assets, the pattern file (when the annotation's sensor fires
        one, copied beside the scene) and the previews.
    """
    objects, ground = load_annotation(annotation)
    model = compose_scene(objects, PrimitiveLibrary.load(library), ground, extent)
    stored = annotation_sensor(annotation)
    sensor, poses = stored if stored is not None else _default_sensor(model)
    xml, *shapes = write_scene_together(model, Path(out_xml), sensor)
    skipped = len(model.info["skipped"])
    console.print(
        f"{len(objects) - skipped:,} objects placed ({skipped:,} skipped: class not in the library), "
        f"{len(model.ellipsoids):,} ellipsoids, {len(model.ground):,} ground triangles -> {xml}"
    )
    return [xml, *shapes, *(render_previews(xml, poses) if preview else ())]
