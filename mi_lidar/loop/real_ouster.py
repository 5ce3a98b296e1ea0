"""The loop on real measured data: one Ouster OS-1-32 frame, a scene fitted from part of it.

Protocol (columns of the destaggered 32 x 1024 range image):

* **scene**: a triangle mesh between neighbouring returns of columns ``0 mod 4``
  (:func:`range_image_mesh`, holes of the range image closed);
* **calibration rays**: columns ``2 mod 4``; every fitted number comes from these;
* **test rays**: the odd columns, scored by their log-likelihood (nats) with ranges in 1 cm bins,
  no-returns by ``log P(miss)`` (:func:`mi_lidar.core.likelihood.score`).

A test ray lies between two mesh columns, so the mesh predicts it by interpolation; the loop then
finds what the interpolating surface lacks (returns from one side of a depth edge, interpolation
error growing with the depth a face spans, lost returns where the image had holes, stray returns)
and adds it. The same protocol serves any one-frame capture of a spinning Lidar (Velodyne too).
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import LOG_FLOOR
from mi_lidar.core.log import Log
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.development import Scored, Step, effect_step, ray_subset
from mi_lidar.scene.dicts import MeshElements, scene_dict

MESH_EVERY = 4  # mesh columns: 0 mod MESH_EVERY; calibration columns: MESH_EVERY / 2 mod MESH_EVERY


FILLED = 1  # lowest label of faces closing a hole of the range image (label: how many of its 3 vertices fill one)


def range_image_mesh(log: Log, columns: np.ndarray, fill_holes: bool = False) -> MeshElements:
    """Triangles between neighbouring returns of a range image restricted to ``columns``.

    Each quad of neighbouring samples (rows ``u, u+1``, consecutive entries of ``columns``; the last
    wraps to the first, as a spinning sensor's image does) gives two triangles, kept where their
    three samples returned. Triangles across depth discontinuities (*jump edges* between a
    foreground and a background return) are kept: no threshold separates them from ground seen at
    grazing incidence (both are seen edge-on, ``|cos|`` 0.02-0.1, with neighbouring ranges 1.2-4x
    apart), and calibrating per-face hit probabilities makes them permeable where rays pass them. On
    the Ouster frame, dropping faces with ``|cos| < 0.02`` or with ``|cos| < 0.1`` and ranges 1.5x
    apart raised the final test NLL (6.205 and 6.219 against 6.180 nats/ray).

    With ``fill_holes`` a sample without a return does not cut a hole into the mesh: it becomes a
    vertex on its own beam at the range of the nearest returning sample (left, right, above, below),
    and each face is labelled by how many of its three vertices are such fills (0: all measured;
    :data:`FILLED` ``= 1`` to 3). A missing return is more often a surface the sensor lost (dark,
    wet, specular, at grazing incidence) than open space: on the Ouster frame 91 % of the test
    returns that met no face of the plain mesh had a returning same-row neighbour, and half of them
    lay within 7 cm of its range. But the more of a face's corners are fills, the more likely the
    face spans open space (sky, out of range) beyond the edge of a surface: on the VLP-16 capture
    (40 % of its test rays return nothing, most of them sky) test rays through faces with 1, 2 and 3
    filled corners return 87 %, 22 % and 5 % of the time (99 % with none). The labels let a dropout
    per label (``label_dropout``) learn that from the calibration rays.

    Args:
        log: a one-scan log (``S = 1``) with a destaggered image: rows are beams, columns azimuth.
        columns: ascending columns whose samples become vertices.
        fill_holes: close holes left by samples without a return (see above).

    Returns:
        Opaque faces (``p_hit`` 1) in the world frame, default range sigma; label the number of
        the face's vertices that fill a hole (0 to 3).
    """
    h = log.shape[1]
    origins, directions = log.origins[0], log.directions[0]
    hit = log.hit[0][:, columns]
    r = np.where(hit, np.nan_to_num(log.ranges[0][:, columns]), np.nan)
    filled = np.zeros_like(hit)
    if fill_holes:
        for du, dv in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            neighbour = np.roll(r, (-du, -dv), axis=(0, 1))
            if du:  # no wrap between the first and the last beam
                neighbour[0 if du < 0 else -1] = np.nan
            take = np.isnan(r) & np.isfinite(neighbour)
            r[take], filled[take] = neighbour[take], True
    valid = np.isfinite(r)
    points = origins[:, columns] + np.nan_to_num(r)[..., None] * directions[:, columns]
    pose = log.poses[0]
    points = points.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    w = len(columns)
    vid = np.arange(h * w).reshape(h, w)
    u, v = np.meshgrid(np.arange(h - 1), np.arange(w), indexing="ij")
    right = (v + 1) % w
    quads = [(vid[u, v], vid[u + 1, v], vid[u, right]), (vid[u + 1, v], vid[u + 1, right], vid[u, right])]
    faces = np.concatenate([np.stack([t.ravel() for t in tri], -1) for tri in quads])
    faces = faces[valid.ravel()[faces].all(axis=1)]
    label = filled.ravel()[faces].sum(axis=1)
    return MeshElements(vertices=points, faces=faces, p_hit=np.ones(len(faces)), label=label)


def column_log(log: Log, columns: np.ndarray) -> Log:
    """The rays of ``columns`` of a one-scan log, as a log of its own (same pose, sensor and per-ray attributes)."""
    cols = np.asarray(columns)
    return Log(
        poses=log.poses,
        directions=log.directions[:, :, cols],
        origins=log.origins[:, :, cols],
        ranges=log.ranges[:, :, cols],
        hit=log.hit[:, :, cols],
        times=log.times[:, :, cols],
        attributes={name: values[:, :, cols] for name, values in log.attributes.items()},
        sensor=dict(log.sensor),
    )


@dataclass
class OusterPath:
    """The development path on the Ouster frame and the final model.

    Attributes:
        rows: one :class:`~mi_lidar.loop.development.Step` per added effect.
        mesh: the final scene elements (faces with their fitted hit probabilities).
        model: the final sensor model (every effect fitted).
    """

    rows: list[Step]
    mesh: MeshElements
    model: SensorModel


def ouster_development_path(log: Log, steps: int = 1500, progress=None) -> OusterPath:
    """Mesh from columns ``0 mod 4`` (holes closed), calibration on columns ``2 mod 4``, test on odd columns.

    Every step adds one effect to the model and refits all effects on the calibration rays; the test
    score is the mean negative log-likelihood per odd-column ray (nats, 1 cm bins), beside the realism
    of a scan sampled at the test rays. A step is kept only when it lowers the calibration NLL without
    making the calibration samples less realistic (the realism guard of
    :func:`~mi_lidar.loop.development.effect_step`). The effects model what the bare mesh misses:

    * ``corner_returns``: at depth edges and in clutter the sensor sees the surface of one of the mesh's
      samples (foreground or background), not the plane between them; its spread is set to the
      sensor's 1 cm, not fitted (see :class:`~mi_lidar.core.effects.corner_returns.CornerReturns`);
    * ``range_noise`` (footprint law): the interpolated plane's error grows with the depth a face spans
      along the beam, ``r tan(incidence)``;
    * ``label_dropout``: faces that close a hole of the range image (labels 1-3: how many corners fill
      one) are where the sensor lost a return, or open space past a surface's edge; they lose returns
      more often, the more so the more corners are fills;
    * ``outliers``: returns no face explains.

    Per-face hit probabilities fitted on the calibration columns (an earlier step of this path) are no
    longer fitted: with corner returns they over-fit the 8,192 calibration rays to 11,000 faces (test
    NLL 5.146 -> 5.460 on the shared frame).

    Args:
        log: a one-scan log of a spinning Lidar (:func:`mi_lidar.io.read_any` of an Ouster or
            Velodyne capture).
        steps: Adam steps per fit.
        progress: optional callable ``progress(message)``.

    Returns:
        The development path and the final model.
    """
    from mi_lidar.core.effects import make_effect

    say = progress or (lambda message: None)
    w = log.shape[2]
    column = np.arange(w)
    mesh = range_image_mesh(log, column[column % MESH_EVERY == 0], fill_holes=True)
    rays = LogRays.from_log(log)
    train_keep, test_keep = rays.column % MESH_EVERY == MESH_EVERY // 2, rays.column % 2 == 1
    scene = mi.load_dict(scene_dict({"map": mesh}))
    table = ElementTable.from_scene(scene)
    train, test = (
        Scored(scene=scene, table=table, rays=ray_subset(rays, keep), n_elements=len(mesh.faces))
        for keep in (train_keep, test_keep)
    )
    say(
        f"mesh: {len(mesh.faces):,} faces from {w // MESH_EVERY:,} columns ({int(np.sum(mesh.label >= FILLED)):,} "
        f"closing holes); {train.rays.n:,} calibration and {test.rays.n:,} test rays"
    )
    model = SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4, effects=[])
    ll = test.per_beam(model)
    rows = [
        Step(
            "range-image mesh, opaque, sigma 1 cm",
            "(mesh only)",
            float(-np.mean(ll)),
            train.nll(model),
            {"test returns at the floor (no face near their range)": int(np.sum(ll <= LOG_FLOOR + 1e-3))},
            test.samples(model),
        )
    ]
    guard = [rows[0].train_nll, train.samples(model)]

    def add(label: str, effect) -> None:
        model.effects = model.effects + [effect]
        row = effect_step("range-image mesh", label, train, test, model, steps, say, guard=tuple(guard))
        rows.append(row)
        if not row.rejected:
            guard[:] = [row.train_nll, train.samples(model)]

    add("corner_returns", make_effect("corner_returns", share=0.5, sigma=0.01))
    add("range_noise (footprint)", make_effect("range_noise", law="footprint", sigma0=0.005, k=0.002))
    add("label_dropout (faces closing holes)", make_effect("label_dropout", drop=[0.02, 0.1, 0.5, 0.9]))
    add("outliers", make_effect("outliers", p_near=0.02, near_scale=2.0, p_uniform=0.005, uniform_max=120.0))
    return OusterPath(rows=rows, mesh=mesh, model=model)
