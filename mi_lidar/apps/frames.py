"""One frame of a spinning Lidar as datasets of the 3D applications: a real scan and simulated scans of the same states.

The protocol is the real-data path of :mod:`mi_lidar.loop.real_ouster`, on the columns of the
frame's range image (rows are beams):

* **scene**: the mesh between the returns of columns ``0 mod 4`` (holes closed,
  :func:`~mi_lidar.loop.real_ouster.range_image_mesh`), the same for every simulator;
* **calibration**: columns ``2 mod 4``; every simulator is fitted on these rays only;
* **map** (what the applications register to): the measured points of the calibration columns;
* **scan**: the rays of the odd columns. The real dataset holds what the sensor measured on them;
  each simulated dataset holds what one simulator samples on the *same rays* (same pose, origins,
  directions and firing times) in the scene.

So for one frame, "the same states" are the test rays, and the map is the same real point cloud for
every source: real and simulated datasets differ only in the sensor model that produced the scan.
A simulated scan of a perfect sensor model would be as useful to an application developer as the
real one, whatever the mesh lacks: the mesh is what every simulator has to work with.

Simulators (:data:`SIMULATORS`), each fitted on the calibration columns:

* ``gaussian``: ideal ray cast plus one Gaussian (Gazebo-style), sigma the robust spread
  (1.4826 MAD) of the calibration residuals;
* ``physics``: the physics baseline (sigma^2 = K r^2 / cos(incidence));
* ``beam``: the classic beam model (hit / short / max / random mixture);
* ``P-Reg`` and ``NP-Reg``: the learned densities (:func:`~mi_lidar.loop.sensor_fit.fit_sensor`);
* ``mi-lidar``: the model calibrated by the loop's development path
  (:func:`~mi_lidar.loop.real_ouster.ouster_development_path`).

Beside the datasets, every simulator gets a row of observation-level losses on the test rays: the
NLL of the measured scan and the realism of its sampled scan (:func:`~mi_lidar.core.metrics.metrics_of`,
Chamfer distance in 3D included).
"""

from __future__ import annotations

import dataclasses

import mitsuba as mi
import numpy as np

from mi_lidar.apps.matching3d import FrameStates, perturbations
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import LogFormatError, ParameterError
from mi_lidar.core.log import Log
from mi_lidar.core.metrics import metrics_of
from mi_lidar.core.params import choose_names
from mi_lidar.core.problem import Problem
from mi_lidar.core.rays import LogRays, world_rays
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.loop.compare import simulate_log_rays
from mi_lidar.loop.real_ouster import MESH_EVERY, column_log, ouster_development_path, range_image_mesh
from mi_lidar.scene.dicts import scene_dict

SIMULATORS = ("gaussian", "physics", "beam", "P-Reg", "NP-Reg", "mi-lidar")
FAMILIES = {"physics": "physics", "beam": "beam", "P-Reg": "p-reg", "NP-Reg": "np-reg"}
MAX_RANGE = 120.0  # m: the simulators' largest range


def one_frame(log: Log) -> Log:
    """The scan of ``log`` with the most returns, as a one-scan log (a capture may start mid-revolution).

    Raises:
        LogFormatError: the scan has fewer than 16 columns (no column split is possible).
    """
    s = int(np.argmax(log.hit.reshape(log.shape[0], -1).sum(axis=1)))
    if log.shape[2] < 4 * MESH_EVERY:
        named = f"{log.source}: the" if log.source else "the"
        raise LogFormatError(
            f"{named} frame has {log.shape[2]} column(s) of {log.shape[1]} beams; the column protocol needs "
            f"{4 * MESH_EVERY} or more: give a 3D frame (an Ouster or Velodyne pcap, or a 3D log), not a planar scan"
        )
    keep = slice(s, s + 1)
    return Log(
        poses=log.poses[keep],
        directions=log.directions[keep] if log.directions.shape[0] > 1 else log.directions,
        origins=log.origins[keep] if log.origins.shape[0] > 1 else log.origins,
        ranges=log.ranges[keep],
        hit=log.hit[keep],
        times=log.times[keep],
        sensor=dict(log.sensor),
    )


def split_columns(log: Log) -> dict[str, np.ndarray]:
    """The protocol's columns of a one-scan log: ``mesh``, ``calibration`` and ``test``."""
    column = np.arange(log.shape[2])
    return {
        "mesh": column[column % MESH_EVERY == 0],
        "calibration": column[column % MESH_EVERY == MESH_EVERY // 2],
        "test": column[column % 2 == 1],
    }


def frame_rays(log: Log) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world-frame origins and directions of every ray of a one-scan log (row-major)."""
    scan, beam, column = (
        a.ravel() for a in np.meshgrid(0, np.arange(log.shape[1]), np.arange(log.shape[2]), indexing="ij")
    )
    return world_rays(log, scan, beam, column)


def frame_states(log: Log, starts: int = 8, seed: int = 0) -> FrameStates:
    """The map (measured calibration points), the test rays and ``starts`` seeded initial-pose errors."""
    columns = split_columns(log)
    calibration, test = column_log(log, columns["calibration"]), column_log(log, columns["test"])
    origins, directions = frame_rays(calibration)
    r = np.where(calibration.hit[0], calibration.ranges[0], np.nan).ravel()
    keep = np.isfinite(r)
    map_points = origins[keep] + r[keep, None] * directions[keep]
    origins, directions = frame_rays(test)
    return FrameStates(map_points, origins, directions, perturbations(starts, seed))


def robust_sigma(problem: Problem, model: SensorModel) -> float:
    """1.4826 x the median absolute deviation of ``measured - nominal`` over the returns that met an element (m)."""
    from mi_lidar.loop.sensor_fit import traced_states

    residual = traced_states(problem, model).residual
    residual = residual[np.isfinite(residual)]
    if residual.size < 10:
        raise ParameterError(f"ray cast + Gaussian: {residual.size} calibration returns met the scene; need 10")
    return float(1.4826 * np.median(np.abs(residual - np.median(residual))))


def fit_simulators(log: Log, simulators=SIMULATORS, steps: int = 1500, progress=None) -> tuple[object, dict]:
    """Fit every simulator on the calibration columns of a one-scan ``log``.

    Args:
        log: the frame.
        simulators: names from :data:`SIMULATORS`.
        steps: Adam steps per fit of the mi-lidar development path.
        progress: optional ``progress(message)``.

    Returns:
        ``(mesh, {name: SensorModel})``: the scene's elements (the mi-lidar path's mesh, with its
        fitted hit probabilities when the path fits them) and each simulator's sensor model.
    """
    from mi_lidar.loop.sensor_fit import fit_sensor

    simulators = choose_names(simulators, SIMULATORS, "unknown 3D simulators")
    say = progress or (lambda message: None)
    columns = split_columns(log)
    mesh = range_image_mesh(log, columns["mesh"], fill_holes=True)
    models: dict[str, SensorModel] = {}
    if "mi-lidar" in simulators:
        path = ouster_development_path(log, steps=steps, progress=say)
        mesh, models["mi-lidar"] = path.mesh, path.model
    scene = mi.load_dict(scene_dict({"map": mesh}))
    calibration = column_log(log, columns["calibration"])
    base = SensorModel(range_sigma=0.01, max_range=MAX_RANGE, max_segments=4)
    if "gaussian" in simulators:
        problem = Problem.build(scene, LogRays.from_log(calibration))
        models["gaussian"] = dataclasses.replace(base, range_sigma=robust_sigma(problem, base))
        say(f"ray cast + Gaussian: sigma {models['gaussian'].range_sigma:.3f} m")
    for name in simulators:
        if name in FAMILIES:
            fitted = fit_sensor(calibration, scene, FAMILIES[name], seed=0)
            models[name] = dataclasses.replace(fitted.model, max_range=MAX_RANGE, max_segments=4)
            say(f"fitted {name}")
    return mesh, {name: models[name] for name in simulators}


def simulated_scans(log: Log, mesh, models: dict, seed: int = 0) -> tuple[dict, list[dict]]:
    """The test columns measured and simulated by every model, with each model's observation-level losses.

    Returns:
        ``(ranges, rows)``: ``{"real": (1, N), name: (1, N)}`` ranges of the test rays (m, NaN: no
        return), and per model its NLL of the measured scan and the realism of its sample
        (:func:`metrics_of` plus ``chamfer``, m).
    """
    test = column_log(log, split_columns(log)["test"])
    rays = LogRays.from_log(test)
    scene = mi.load_dict(scene_dict({"map": mesh}))
    table = ElementTable.from_scene(scene)
    problem = Problem.build(scene, rays, table=table)
    origins, directions = frame_rays(test)
    measured = np.where(rays.hit, rays.measured, np.nan)
    ranges, rows = {"real": measured[None]}, []
    for name, model in models.items():
        sim_range, sim_hit = simulate_log_rays(scene, table, rays, model, seed)
        ranges[name] = np.where(sim_hit, sim_range, np.nan)[None]
        ll = problem.log_likelihood(model)
        row = metrics_of(ll, rays.measured, rays.hit, sim_range, sim_hit, origins, directions)
        rows.append({"model": name, **row})
    return ranges, rows
