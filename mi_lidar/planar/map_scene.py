"""The permeable wall map of a planar log, written as a Mitsuba scene: ``mi-lidar fit-scene`` on a planar log.

A planar scanner (a SICK LMS: every beam in one horizontal plane) sees a 2D world, so its scene is a map of
that plane. The map is the log's own occupancy counts, counted as the real-planar protocol counts them
(:func:`mi_lidar.planar.grid.count_scans`, ``docs/benchmark_planar.md``): on a grid of ``cell`` m, every return
adds a *hit* to the cell it ends in and a *pass-through* to every cell its beam crosses up to one cell short of
that; a no-return clears nothing (a dark or glancing surface is silent too, not only free space). Unlike the
benchmark's maps, every return counts, however far, and the grid spans them all.

Every cell with a hit becomes a vertical box from :data:`HALF_HEIGHT` below to :data:`HALF_HEIGHT` above the
scan plane (the poses' median height), side faces only (a planar beam never meets a top or bottom; ±0.5 m
tolerates a scanner that tilts by a degree out to 28 m). The box stops a beam that reaches it with

    p = (hits + a) / (hits + passes + a + b),   Beta prior (a, b) = :data:`PRIOR` = (1, 0.1):

the counting estimate, pulled towards a wall for cells seen rarely: a cell hit once and never passed gets
0.95, a wall hit 20 times and never passed 0.995, a cell hit once and passed 20 times (a person's legs)
0.09. (A symmetric prior, Beta(0.5, 0.5), lets 2-5 % of the beams through walls seen 10-20 times; on the Intel
log, scored on itself by ``compare``, it explains some no-returns by such leaks, NLL 3.32 against 3.37 nats/ray,
but samples returns from behind the walls: histogram L1 0.093 against 0.062 m, p90 |range error| 0.336 against
0.308 m.) A beam crosses two side faces of a box, so each face stops it with ``q = 1 - sqrt(1 - p)``
(:func:`face_p_hit`): ``1 - (1 - q)^2 = p``. Neighbouring boxes share a face; it is written once, with
``1 - (1 - q_1)(1 - q_2)``, so a beam that crosses both boxes passes with the same ``(1 - q_1)^2 (1 - q_2)^2``
and no two triangles coincide (Embree would report coincident triangles in either order).

The scene's sensor fires the log's pattern (scan 0) from its first pose, its ``max_range`` is the log's
no-return value (detected by the reader, :func:`mi_lidar.io.carmen.detect_max_range`; without one, the
largest return rounded up to the metre), and its ``range_sigma`` (every face takes the sensor's) starts at
half a cell (:data:`SIGMA_PER_CELL`): a beam stops at a cell's faces while the surface lies anywhere in the
cell, and the scanner's own noise (about 1 cm for a SICK LMS) is the smaller part. On the Intel log (5 cm
cells, ``compare`` on itself) 0.02, 0.025, 0.03 and 0.05 m score 3.371, 3.371, 3.391 and 3.534 nats/ray;
``fit-sensor``, ``diagnose`` and ``calibrate`` refine it.

A map built from a log and scored on the same log is in-sample: every measured return has a box at its end
point. ``benchmark-planar`` scores maps that leave out each test scan's neighbourhood.

Example::

    log = read_any("intel-corrected.log.gz")
    xml, ply, pattern, *previews = fit_map_scene(log, "out/intel")
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.table import Table

from mi_lidar.core.errors import LogFormatError, ParameterError
from mi_lidar.core.frames import local_origin
from mi_lidar.core.log import Log
from mi_lidar.core.poses import validate_poses
from mi_lidar.hybrid.blocks import SceneSensor, assets_folder
from mi_lidar.hybrid.commands import console, progress_bar, render_previews, write_staged
from mi_lidar.planar.beams import permeability
from mi_lidar.planar.grid import Grid, check_planar_shape, count_scans
from mi_lidar.planar.protocol import map_grid
from mi_lidar.scene.files import ShapeEntry, write_mesh_ply, write_scene_xml

CELL = 0.05  # m: map cell (the protocol's)
HALF_HEIGHT = 0.5  # m: the boxes reach this far below and above the scan plane
PRIOR = (1.0, 0.1)  # Beta prior (a, b) of a cell's hit probability: a cell seen once is a wall
SIGMA_PER_CELL = 0.5  # the sensor's range sigma to start from, in cells
MAX_SEGMENTS = 128  # faces a beam may pass before it counts as a miss (Intel: up to 97 cells before a return)
LABEL = 1  # the walls' label
STILL_SPREAD = 0.25  # m: median spread of a beam's returns between scans above which a log at one pose moved
OFF_PLANE = 0.01  # share of the returns that may lie more than HALF_HEIGHT from the scan plane
SAMPLES_PER_CHUNK = 5_000_000  # beam samples a counting thread marches at once (about 100 bytes each at its peak)


@dataclass
class WallMap:
    """The cells of a planar log with a hit, and how often they stopped the beams that reached them.

    Attributes:
        grid: the map grid.
        cells: (C,) flat indices of the cells with at least one hit, ascending.
        hits, passes: (C,) endpoint hits and pass-throughs of each cell.
        plane_z: height of the scan plane (m): the poses' median height.
    """

    grid: Grid
    cells: np.ndarray
    hits: np.ndarray
    passes: np.ndarray
    plane_z: float

    @property
    def p_hit(self) -> np.ndarray:
        """(C,) probability that the cell stops a beam that reaches it, under the Beta :data:`PRIOR`."""
        return permeability(self.hits, self.passes, *PRIOR)


def face_p_hit(p: np.ndarray) -> np.ndarray:
    """The hit probability ``q = 1 - sqrt(1 - p)`` of each of two faces that together stop a beam with ``p``."""
    return 1.0 - np.sqrt(1.0 - np.asarray(p, np.float64))


def count_walls(log: Log, cell: float = CELL, progress=None) -> WallMap:
    """Count the hits and pass-throughs of every cell of ``log`` that holds a return (see the module docstring).

    Args:
        log: a planar log (S scans x N beams x 1 firing, world poses).
        cell: grid cell, m.
        progress: ``progress(done, total)`` over the scans, or None.
    """
    if not 0.005 <= cell <= 1.0:
        raise ParameterError(f"cell={cell} m must lie in [0.005, 1], e.g. {CELL}")
    grid = map_grid(log, cell, reach=np.inf, trim=0.0)
    marched = np.nansum(np.where(log.hit, log.ranges, 0.0)) / log.shape[0] / (cell / 4)  # samples per scan
    chunk = int(np.clip(SAMPLES_PER_CHUNK / max(marched, 1.0), 1, 64))
    counts = count_scans(log, grid, reach=np.inf, chunk=chunk, progress=progress, workers=os.cpu_count() or 1)
    cells, hits = np.unique(counts.hit_cell.astype(np.int64), return_counts=True)
    passes = np.bincount(np.searchsorted(cells, counts.pass_cell), minlength=cells.size)  # passes: only hit cells
    return WallMap(grid, cells, hits, passes, float(np.median(log.poses[:, 2, 3])))


def wall_faces(walls: WallMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The side faces of the cells' boxes as a triangle mesh, each shared face once.

    Returns:
        (V, 3) vertices (m, world), (F, 3) triangles (two per face) and (F,) their hit probabilities.
    """
    nx, ny = walls.grid.shape
    i, j = walls.cells // ny, walls.cells % ny
    # A face is a grid line between two cells: x = I (I in 0..nx) along row j, or y = J along column i. Its key
    # numbers vertical faces I * ny + j, then horizontal ones after them.
    vertical = lambda line, row: line * ny + row  # noqa: E731
    horizontal = lambda col, line: (nx + 1) * ny + col * (ny + 1) + line  # noqa: E731
    keys = np.concatenate([vertical(i, j), vertical(i + 1, j), horizontal(i, j), horizontal(i, j + 1)])
    survival = np.tile(0.5 * np.log1p(-walls.p_hit), 4)  # log(1 - q) of the cell's face
    keys, at = np.unique(keys, return_inverse=True)
    p_face = -np.expm1(np.bincount(at, weights=survival))
    is_vertical = keys < (nx + 1) * ny
    h = keys - (nx + 1) * ny
    # the face's two grid corners (integer corner coordinates)
    a = np.where(is_vertical[:, None], np.stack([keys // ny, keys % ny], 1), np.stack([h // (ny + 1), h % (ny + 1)], 1))
    b = a + np.where(is_vertical[:, None], [0, 1], [1, 0])
    corners, index = np.unique(np.concatenate([a, b]), axis=0, return_inverse=True)
    index = index.reshape(2, -1)
    xy = np.asarray(walls.grid.origin) + corners * walls.grid.cell
    z = walls.plane_z + np.array([-HALF_HEIGHT, HALF_HEIGHT])
    vertices = np.concatenate([np.c_[xy, np.full(len(xy), z[0])], np.c_[xy, np.full(len(xy), z[1])]])
    lo_a, lo_b, hi_a, hi_b = index[0], index[1], index[0] + len(xy), index[1] + len(xy)
    triangles = np.concatenate([np.stack([lo_a, lo_b, hi_b], 1), np.stack([lo_a, hi_b, hi_a], 1)])
    return vertices, triangles, np.tile(p_face, 2)


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
    _check_moved(log, source)
    _check_plane(log, source)


def _check_moved(log: Log, source) -> None:
    """Refuse a log whose scans all share one pose while the same beam's returns differ between them."""
    if log.shape[0] < 2 or not np.all(log.poses == log.poses[0]):
        return
    z = np.where(log.hit[:, :, 0], log.ranges[:, :, 0], np.nan)
    seen = np.isfinite(z).sum(axis=0) >= 2
    if not seen.any():
        return
    z = z[:, seen]
    spread = float(np.median(np.nanmedian(np.abs(z - np.nanmedian(z, axis=0)), axis=0)))
    if spread > STILL_SPREAD:
        which = "the identity" if np.allclose(log.poses[0], np.eye(4)) else "one pose"
        raise LogFormatError(
            f"{source}: all {log.shape[0]:,} scans have the same pose ({which}), yet a beam's returns differ between "
            f"scans by a median {spread:.2f} m: the scanner moved and the log has no poses, so the map would be a "
            "smear of every scan. Give a log with SLAM-corrected poses (CARMEN FLASER lines, or the .gfs.log a "
            f"SLAM such as GMapping writes); a scanner that stood still gives under {STILL_SPREAD:g} m and is mapped"
        )


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
        walls = count_walls(log, cell, progress=lambda done, total: report("counting hits and passes", done / total))
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
            f"mi-lidar wall map of {Path(source).name}: {walls.cells.size} cells of {walls.grid.cell:g} m, "
            f"{len(triangles) // 2} faces from z = {walls.plane_z - HALF_HEIGHT:g} to {walls.plane_z + HALF_HEIGHT:g} m"
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
    table.add_row("cells with a hit", f"{walls.cells.size:,} of {walls.grid.cell:g} m")
    table.add_row("hits / pass-throughs", f"{int(walls.hits.sum()):,} / {int(walls.passes.sum()):,}")
    table.add_row("cell p_hit: median, share > 0.5", f"{np.median(p):.2f}, {np.mean(p > 0.5):.0%}")
    table.add_row(
        "triangles, z (m)", f"{n_triangles:,}, {walls.plane_z - HALF_HEIGHT:g} to {walls.plane_z + HALF_HEIGHT:g}"
    )
    table.add_row("sensor max range, sigma (m)", f"{sensor.max_range:g}, {sensor.range_sigma:g}")
    table.add_row("time (s)", f"{seconds:.1f}")
    console.print(table)
