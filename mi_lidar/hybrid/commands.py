"""Command functions of the hybrid-scene tools (plain functions; the CLI wires them to Typer).

Examples::

    fit_scene("train.npz", "out/train_scene")               # -> out/train_scene/scene.xml
    primitives_extract("train.npz", "library")              # labelled log -> primitive library
    primitives_list("library")                              # table of primitives
    primitives_show("library", "library.png")               # preview PNG
    annotate("test.npz", "test_annotation.json")            # labelled log -> annotation + ground
    compose("test_annotation.json", "library", "out/test.xml")
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from ..errors import LogFormatError
from ..log import Log
from .blocks import write_scene
from .compose import annotation_from_segments, compose_scene, load_annotation, save_annotation
from .fit import FitParams, FitResult, fit_model
from .primitives import PrimitiveLibrary, extract_primitives
from .segments import segments_from_labels

console = Console(stderr=True)


@contextmanager
def progress_bar(title: str):
    """A rich progress bar; yields a ``progress(stage, fraction)`` callback for :func:`fit_model`."""
    with Progress(TextColumn(f"{title}: [bold]{{task.description}}"), BarColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task("start", total=1.0)
        yield lambda stage, fraction: bar.update(task, description=stage, completed=fraction)


def _fit(log: Log, params: FitParams | None, title: str, ground_only: bool = False) -> FitResult:
    with progress_bar(title) as report:
        return fit_model(log, params, report, ground_only=ground_only)


def _require_labels(log: Log, path) -> None:
    missing = [k for k in ("label", "instance") if k not in log.attributes]
    if missing:
        raise LogFormatError(f"{path}: the log has no {missing} attributes; primitives and annotations need a "
                             "labelled log (e.g. a synthetic log from mi_lidar.hybrid.world.render_log)")


def fit_scene(log_path, out_dir, params: FitParams | None = None, name: str = "scene") -> Path:
    """Fit a hybrid model to the log at ``log_path`` and write ``<out_dir>/<name>.xml``; return its path."""
    log = Log.load(log_path)
    result = _fit(log, params, "fit")
    xml = write_scene(result.model, out_dir, name)
    table = Table(title=f"hybrid scene {xml}")
    for col in ("points", "ground points", "triangles", "ellipsoids", "blocks", "seconds"):
        table.add_column(col, justify="right")
    table.add_row(str(len(result.points)), str(int(result.is_ground.sum())), str(len(result.model.ground)),
                  str(len(result.model.ellipsoids)), str(result.model.info["n_blocks"]),
                  f"{sum(result.timings.values()):.1f}")
    console.print(table)
    return xml


def primitives_extract(log_path, library_dir, params: FitParams | None = None) -> PrimitiveLibrary:
    """Fit the labelled log, cut its objects into primitives and add them to ``library_dir``."""
    log = Log.load(log_path)
    _require_labels(log, log_path)
    result = _fit(log, params, "extract")
    labels = log.attributes["label"].ravel()[result.ray_index]
    inst = log.attributes["instance"].ravel()[result.ray_index]
    segs = segments_from_labels(result.points, labels, inst)
    library = PrimitiveLibrary.load(library_dir) if (Path(library_dir) / "library.json").is_file() else PrimitiveLibrary()
    library.add(extract_primitives(result.model, result.points, segs, log.poses, source=Path(log_path).stem))
    library.save(library_dir)
    console.print(f"{len(library)} primitives in {library_dir}")
    return library


def primitives_list(library_dir) -> list[dict]:
    """Print and return a summary row per primitive of the library at ``library_dir``."""
    rows = PrimitiveLibrary.load(library_dir).rows()
    table = Table(title=str(library_dir))
    for col in ("id", "class", "ellipsoids", "extents (m)"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["id"], r["class"], str(r["ellipsoids"]), " x ".join(f"{x:.2f}" for x in r["extents"]))
    console.print(table)
    return rows


def primitives_show(library_dir, out_png, ids: list[str] | None = None, per_class: int = 4) -> Path:
    """Write a preview PNG of primitives (all classes, or ``ids``); return its path."""
    return PrimitiveLibrary.load(library_dir).preview(out_png, per_class=per_class, ids=ids)


def annotate(log_path, out_json, params: FitParams | None = None) -> Path:
    """Annotation (objects from the log's labels, ground mesh fitted to its ground points) of a log."""
    log = Log.load(log_path)
    _require_labels(log, log_path)
    result = _fit(log, params, "annotate", ground_only=True)
    labels = log.attributes["label"].ravel()[result.ray_index]
    inst = log.attributes["instance"].ravel()[result.ray_index]
    objects = annotation_from_segments(result.points, segments_from_labels(result.points, labels, inst), log.poses)
    return save_annotation(out_json, objects, result.model.ground)


def compose(annotation, library, out_xml, extent: float = 3.5) -> Path:
    """Build the scene of ``annotation`` from the primitive library folder ``library``; write ``out_xml``."""
    objects, ground = load_annotation(annotation)
    model = compose_scene(objects, PrimitiveLibrary.load(library), ground, extent)
    out_xml = Path(out_xml)
    return write_scene(model, out_xml.parent, out_xml.stem)
