"""The permeable wall map of a planar log, written as a Mitsuba scene: ``mi-lidar fit-scene`` on a planar log.

The map (:mod:`mi_lidar.planar.wall_map`) is the log's own counts on a grid of 5 cm cells: every cell a return
ended in holds one element from 0.5 m below to 0.5 m above the scan plane that stops a beam with the share of the
beams reaching it that stopped there, ``(hits + 1) / (hits + passes + 1.1)``; a quad through the cell's hits where
the hits around it lie on a line (a wall), the cell's box elsewhere. The elements are one triangle mesh
(``<name>_assets/walls.ply``, per-face ``p_hit`` and label :data:`LABEL`) in the log's world frame.

The scene's sensor fires the log's pattern (scan 0) from its first pose, its ``max_range`` is the log's
no-return value (detected by the reader, :func:`mi_lidar.io.carmen.detect_max_range`; without one, the
largest return rounded up to the metre), and its ``range_sigma`` (every face takes the sensor's) starts at
half a cell (:data:`SIGMA_PER_CELL`): a beam stops at a box's faces while the surface lies anywhere in the
cell, and a grazing beam meets a wall's surface several centimetres from its return (1 cm across the wall is
6 cm along a beam at 80 deg); the scanner's own noise (about 1 cm for a SICK LMS) is the smaller part. On the
Intel log (5 cm cells, ``compare`` on itself) 0.015, 0.02 and 0.025 m score 3.289, 3.220 and 3.219 nats/ray
(with cell boxes everywhere: 0.02, 0.025, 0.03 and 0.05 m scored 3.371, 3.371, 3.391 and 3.534);
``fit-sensor``, ``diagnose`` and ``calibrate`` refine it.

A map built from a log and scored on the same log is in-sample: every measured return has an element at or near
its end point. ``benchmark-planar`` scores maps that leave out each test scan's neighbourhood.

Example::

    log = read_any("intel-corrected.log.gz")
    xml, ply, pattern, *previews = fit_map_scene(log, "out/intel")
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from rich.table import Table

from mi_lidar.core.errors import LogFormatError, ParameterError
from mi_lidar.core.frames import local_origin
from mi_lidar.core.log import Log
from mi_lidar.core.poses import validate_poses
from mi_lidar.hybrid.blocks import SceneSensor, assets_folder
from mi_lidar.hybrid.commands import console, progress_bar, render_previews, write_staged
from mi_lidar.planar.grid import check_moved, check_planar_shape
from mi_lidar.planar.wall_map import CELL, HALF_HEIGHT, WallMap, count_walls, wall_faces
from mi_lidar.scene.files import ShapeEntry, write_mesh_ply, write_scene_xml

SIGMA_PER_CELL = 0.5  # the sensor's range sigma to start from, in cells
MAX_SEGMENTS = 128  # faces a beam may pass before it counts as a miss (Intel: up to 97 cells before a return)
LABEL = 1  # the walls' label
OFF_PLANE = 0.01  # share of the returns that may lie more than HALF_HEIGHT from the scan plane


def check_map_log(log: Log, source) -> None:
    """Refuse a planar log that cannot make a wall map, saying what to give instead.

    Raises:
        ParameterError: the log is not one planar pattern of N beams x 1 firing.
        PoseError: a pose that is not a finite rigid transform.
        LogFormatError: no return at all; every scan at one pose while the scans differ (a log without poses);
            returns off the scan plane (tilting or climbing scans).
    """
    if not log.is_planar:
        raise ParameterError(
            f"{source}: not a planar log (its beams leave the sensor's xy plane); a wall map needs a 2D scanner's log, "
            "a 3D log gets a hybrid scene (mi_lidar.hybrid.commands.fit_scene)"
        )
    check_planar_shape(log)
    validate_poses(log.poses, source)
    if not log.hit.any():
        no_return = _no_return(log)
        code = f" or at its no-return value {no_return:g} m" if np.isfinite(no_return) else ""
        raise LogFormatError(
            f"{source}: none of the log's {log.hit.size:,} readings is a return (every one is <= 0{code}), so there "
            "are no walls to map: check that the ranges are in metres and that the log holds the scanner's readings"
        )
    check_moved(log, source)
    _check_plane(log, source)


def _check_plane(log: Log, source) -> None:
    """Refuse a log whose returns leave the boxes: more than :data:`OFF_PLANE` of them beyond :data:`HALF_HEIGHT`."""
    z = np.where(log.hit, log.ranges, 0.0)[..., None] * log.directions + log.origins  # sensor frame (S, N, 1, 3)
    height = np.einsum("sj,snwj->snw", log.poses[:, 2, :3], z) + log.poses[:, None, None, 2, 3]
    plane = float(np.median(log.poses[:, 2, 3]))
    off = log.hit & (np.abs(height - plane) > HALF_HEIGHT)
    if off.sum() > OFF_PLANE * log.hit.sum():
        scan = int(np.argmax(off.sum(axis=(1, 2))))
        tilt = float(np.degrees(np.arccos(np.clip(log.poses[scan, 2, 2], -1.0, 1.0))))
        raise LogFormatError(
            f"{source}: {off.sum() / log.hit.sum():.1%} of the returns lie more than {HALF_HEIGHT:g} m above or below "
            f"the scan plane at z = {plane:g} m (scan {scan}: the sensor at z = {log.poses[scan, 2, 3]:g} m, tilted "
            f"{tilt:.1f} deg): a wall map is one horizontal plane; a log whose scans tilt or climb needs a 3D scene"
        )


def _no_return(log: Log) -> float:
    """The log's no-return value (m; ``inf`` when it has none)."""
    return float(log.sensor.get("max_range_m", log.sensor.get("max_range", np.inf)))


def map_sensor(log: Log, cell: float) -> SceneSensor:
    """The scene's sensor: at the log's first pose, its no-return value (or largest return, rounded up) as
    ``max_range``, a range sigma of :data:`SIGMA_PER_CELL` times ``cell`` (m); its pattern is set from the log
    when written (:func:`write_staged`)."""
    no_return = _no_return(log)
    max_range = no_return if np.isfinite(no_return) else float(np.ceil(np.nanmax(log.ranges[log.hit])))
    return SceneSensor(
        pattern="",
        pose=log.poses[0],
        min_range=float(log.sensor.get("min_range", 0.0)),
        max_range=max_range,
        range_sigma=SIGMA_PER_CELL * cell,
        max_segments=MAX_SEGMENTS,
    )


def fit_map_scene(log: Log, out_dir, name: str = "scene", cell: float = CELL, preview: bool = True) -> list[Path]:
    """Count ``log``'s wall map and write it as ``<out_dir>/<name>.xml`` (see the module docstring).

    Args:
        log: a planar log with world poses (e.g. a SLAM-corrected CARMEN log read by
            :func:`mi_lidar.io.dispatch.read_any`).
        out_dir: output folder.
        name: XML file stem; the mesh goes to ``<name>_assets/walls.ply``, the pattern to
            ``<name>_assets/pattern.npy``.
        cell: map cell, m.
        preview: also render ``<name>_range.png`` and ``<name>_top.png`` (20 of the log's poses).

    Returns:
        The paths written: the XML, the mesh, the pattern table, then the previews.
    """
    source = log.source or "log"
    check_map_log(log, source)
    start = time.perf_counter()
    with progress_bar("wall map") as report:
        walls = count_walls(log, cell, progress=report)
    vertices, triangles, p_face = wall_faces(walls)
    origin = local_origin(vertices)  # zero unless the log is georeferenced (float32 vertices keep millimetres)
    to_world = None
    if np.any(origin):
        to_world = np.eye(4)
        to_world[:3, 3] = origin

    def write(folder: Path, stem: str, sensor: SceneSensor) -> list[Path]:
        assets = assets_folder(folder, stem)
        mesh = write_mesh_ply(assets / "walls.ply", vertices - origin, triangles, p_hit=p_face, label=LABEL)
        entry = ShapeEntry(id="walls", kind="mesh", filename=f"{assets.name}/walls.ply", to_world=to_world)
        comment = (
            f"mi-lidar wall map of {Path(source).name}: {walls.cells.size} cells of {walls.grid.cell:g} m "
            f"({int(walls.surface.sum())} surfaces, the rest boxes), {len(triangles) // 2} quads from "
            f"z = {walls.plane_z - HALF_HEIGHT:g} to {walls.plane_z + HALF_HEIGHT:g} m"
        )
        xml = write_scene_xml(folder / f"{stem}.xml", [entry], header_comment=comment, extra_xml=sensor.xml())
        return [xml, mesh]

    sensor = map_sensor(log, cell)
    written = write_staged(Path(out_dir) / f"{name}.xml", write, sensor, log)
    _print_summary(written[0], walls, sensor, len(triangles), time.perf_counter() - start)
    return [*written, *(render_previews(written[0], log.poses) if preview else ())]


def _print_summary(xml: Path, walls: WallMap, sensor: SceneSensor, n_triangles: int, seconds: float) -> None:
    table = Table(title=f"wall map {xml}", header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    p = walls.p_hit
    surface = walls.surface
    table.add_row(f"cells of {walls.grid.cell:g} m: surfaces / boxes", f"{surface.sum():,} / {(~surface).sum():,}")
    table.add_row("hits in surfaces / boxes", f"{walls.hits[surface].sum():,} / {walls.hits[~surface].sum():,}")
    table.add_row("pass-throughs", f"{int(walls.passes.sum()):,}")
    table.add_row("p_hit: median, share > 0.5", f"{np.median(p):.2f}, {np.mean(p > 0.5):.0%}")
    table.add_row(
        "triangles, z (m)", f"{n_triangles:,}, {walls.plane_z - HALF_HEIGHT:g} to {walls.plane_z + HALF_HEIGHT:g}"
    )
    table.add_row("sensor max range, sigma (m)", f"{sensor.max_range:g}, {sensor.range_sigma:g}")
    table.add_row("time (s)", f"{seconds:.1f}")
    console.print(table)
