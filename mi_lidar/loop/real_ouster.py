"""The loop on real measured data: one Ouster OS-1-32 frame, a scene fitted from part of it.

Protocol (columns of the destaggered 32 x 1024 range image):

* **scene**: a triangle mesh between neighbouring returns of columns ``0 mod 4``
  (:func:`range_image_mesh`);
* **calibration rays**: columns ``2 mod 4``; every fitted number (effect parameters, per-face hit
  probabilities) comes from these;
* **test rays**: the odd columns, scored by their log-likelihood (nats) with ranges in 1 cm bins,
  no-returns by ``log P(miss)`` (:func:`mi_lidar.core.likelihood.score`).

A test ray lies between two mesh columns, so the mesh predicts it by interpolation; the loop then
finds what the interpolating surface lacks (stray returns, range noise, permeable or missing
surfaces, dropouts) and adds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from mi_lidar.calibration.fit import Calibration, FitOptions
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.likelihood import LOG_FLOOR
from mi_lidar.core.log import Log
from mi_lidar.core.rays import LogRays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.development import Scored, Step, effect_step, ray_subset
from mi_lidar.scene.dicts import MeshElements, scene_dict

MESH_EVERY = 4  # mesh columns: 0 mod MESH_EVERY; calibration columns: MESH_EVERY / 2 mod MESH_EVERY


def range_image_mesh(log: Log, columns: np.ndarray) -> MeshElements:
    """Triangles between neighbouring returns of a range image restricted to ``columns``.

    Each quad of neighbouring returns (rows ``u, u+1``, consecutive entries of ``columns``; the last
    wraps to the first, as a spinning sensor's image does) with four returns gives two triangles.
    Triangles across depth discontinuities (*jump edges* between a foreground and a background
    return) are kept: no threshold separates them from ground seen at grazing incidence (both are
    seen edge-on, ``|cos|`` 0.02-0.1, with neighbouring ranges 1.2-4x apart), and calibrating
    per-face hit probabilities makes them permeable where rays pass them. On the Ouster frame,
    dropping faces with ``|cos| < 0.02`` or with ``|cos| < 0.1`` and ranges 1.5x apart raised the
    final test NLL (6.205 and 6.219 against 6.180 nats/ray).

    Args:
        log: a one-scan log (``S = 1``) with a destaggered image: rows are beams, columns azimuth.
        columns: ascending columns whose returns become vertices.

    Returns:
        Opaque faces (``p_hit`` 1) in the world frame, default range sigma.
    """
    h = log.shape[1]
    origins, directions = log.origins[0], log.directions[0]
    r = np.nan_to_num(log.ranges[0][:, columns])
    hit = log.hit[0][:, columns]
    points = origins[:, columns] + r[..., None] * directions[:, columns]
    pose = log.poses[0]
    points = points.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    w = len(columns)
    vid = np.arange(h * w).reshape(h, w)
    u, v = np.meshgrid(np.arange(h - 1), np.arange(w), indexing="ij")
    right = (v + 1) % w
    quads = [(vid[u, v], vid[u + 1, v], vid[u, right]), (vid[u + 1, v], vid[u + 1, right], vid[u, right])]
    faces = np.concatenate([np.stack([t.ravel() for t in tri], -1) for tri in quads])
    faces = faces[hit.ravel()[faces].all(axis=1)]
    return MeshElements(vertices=points, faces=faces, p_hit=np.ones(len(faces)), label=np.zeros(len(faces)))


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


def counted_hit_probabilities(
    mesh: MeshElements, log: Log, model: SensorModel, steps: int, seed: int = 0
) -> np.ndarray:
    """Per-face hit probabilities fitted to ``log`` by the calibration layer (``elements.*.p_hit``).

    The counting estimate ``hits / (hits + pass-throughs)`` starts Adam on the log's likelihood
    (:class:`~mi_lidar.calibration.fit.Calibration`, 20 % of the rays held out for early stopping).

    Returns:
        (F,) hit probabilities, in the order of ``mesh.faces``.
    """
    scene = mi.load_dict(scene_dict({"map": mesh}))
    calibration = Calibration(
        scene,
        log,
        ["elements.*.p_hit"],
        model=model,
        options=FitOptions(steps=steps, seed=seed, eval_every=10, patience=3),
    )
    result = calibration.fit()
    (name,) = result.names
    return np.asarray(result.fitted[name], dtype=np.float64)


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
    """Mesh from columns ``0 mod 4``, calibration on columns ``2 mod 4``, test on odd columns.

    Every step adds one effect (or the per-face hit probabilities) to the model and refits all
    effects on the calibration rays; the test score is the mean negative log-likelihood per
    odd-column ray (nats, 1 cm bins).

    Args:
        log: the one-scan Ouster log (:func:`mi_lidar.io.read_any` of the pcap).
        steps: Adam steps per fit.
        progress: optional callable ``progress(message)``.

    Returns:
        The development path and the final model.
    """
    from mi_lidar.core.effects import make_effect

    say = progress or (lambda message: None)
    w = log.shape[2]
    column = np.arange(w)
    mesh = range_image_mesh(log, column[column % MESH_EVERY == 0])
    rays = LogRays.from_log(log)
    train_keep, test_keep = rays.column % MESH_EVERY == MESH_EVERY // 2, rays.column % 2 == 1

    def scored(elements: MeshElements) -> tuple[Scored, Scored]:
        scene = mi.load_dict(scene_dict({"map": elements}))
        table = ElementTable.from_scene(scene)
        return tuple(
            Scored(scene=scene, table=table, rays=ray_subset(rays, keep), n_elements=len(elements.faces))
            for keep in (train_keep, test_keep)
        )

    train, test = scored(mesh)
    say(
        f"mesh: {len(mesh.faces)} faces from {w // MESH_EVERY} columns; {train.rays.n} calibration and "
        f"{test.rays.n} test rays"
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
        )
    ]

    def add(label: str, effect=None) -> None:
        if effect is not None:
            model.effects = model.effects + [effect]
        rows.append(effect_step("range-image mesh", label, train, test, model, steps, say))

    add("outliers", make_effect("outliers", p_near=0.02, near_scale=2.0, p_uniform=0.005, uniform_max=120.0))
    add("range_noise (proportional)", make_effect("range_noise", law="proportional", sigma0=0.02, k=0.002))
    mesh = MeshElements(
        vertices=mesh.vertices,
        faces=mesh.faces,
        label=mesh.label,
        p_hit=counted_hit_probabilities(
            mesh, column_log(log, column[column % MESH_EVERY == MESH_EVERY // 2]), model, steps
        ),
    )
    train, test = scored(mesh)
    add("permeability (per-face p_hit: counting, then Adam)")
    add("incidence_dropout", make_effect("incidence_dropout", gamma=0.3))
    add("range_dropout", make_effect("range_dropout", rate=0.05, power=2.0))
    return OusterPath(rows=rows, mesh=mesh, model=model)
