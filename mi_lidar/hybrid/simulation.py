"""A hybrid model in the product's simulation core: scene, simulation of logged rays, traversal.

The model becomes a Mitsuba scene through the calibration layer
(:func:`mi_lidar.scene.dicts.scene_dict`): one triangle mesh ``ground`` with per-face
``p_hit``, ``range_sigma`` and ``label``, and one ``ellipsoids`` shape with per-ellipsoid
``p_hit`` and ``label``. Simulation is :func:`mi_lidar.simulate` with the log's own firing
pattern and poses, so every number of this package comes from the same core as ``mi.render``.
:func:`trace_elements` lists the elements met along logged rays with the core's one tracer and
element table (used to count hits and pass-throughs when fitting).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.elements import ElementTable
from mi_lidar.core.log import Log
from mi_lidar.core.patterns.from_log import pattern_from_log
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.core.trace import trace_rounds
from mi_lidar.hybrid.model import HybridModel
from mi_lidar.scene.dicts import EllipsoidElements, MeshElements, scene_dict
from mi_lidar.scene.loading import load_scene
from mi_lidar.scene.simulation import simulate

GROUND_ID = "ground"
ELLIPSOIDS_ID = "ellipsoids"


def element_sets(model: HybridModel) -> dict:
    """``{shape id: element set}`` of the non-empty parts of ``model`` (see module docstring)."""
    sets = {}
    g, e = model.ground, model.ellipsoids
    if len(g):
        sets[GROUND_ID] = MeshElements(g.vertices, g.faces, g.p_hit, g.label, g.range_sigma)
    if len(e):
        scales, quats = e.axes()
        sets[ELLIPSOIDS_ID] = EllipsoidElements(e.means, scales, quats, e.p_hit, e.label, model.extent)
    return sets


def load_model(model: HybridModel):
    """The Mitsuba scene of ``model`` (loaded with :func:`mi_lidar.load_scene`)."""
    return load_scene(scene_dict(element_sets(model)))


def log_sensor_model(log: Log, max_segments: int = 16) -> SensorModel:
    """Sensor model with the log's range limits (``min_range``/``max_range`` metadata, m)."""
    return SensorModel(
        min_range=float(log.sensor.get("min_range", 0.0)),
        max_range=float(log.sensor.get("max_range", 120.0)),
        max_segments=max_segments,
    )


def simulate_log(scene, log: Log, seed: int = 0, sensor: SensorModel | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Simulate every ray of ``log`` in ``scene`` with :func:`mi_lidar.simulate`.

    Args:
        scene: a loaded scene, a scene XML path, or a :class:`HybridModel`.
        log: the log whose firing pattern (scan 0) and poses are replayed.
        seed: random seed.
        sensor: sensor model (default: :func:`log_sensor_model`).

    Returns:
        (S, H, W) simulated ranges, m (NaN = miss), and (S, H, W) int32 class label of the
        returning element (0 = miss).
    """
    if isinstance(scene, HybridModel):
        scene = load_model(scene)
    out = simulate(scene, pattern_from_log(log), log.poses, seed, sensor or log_sensor_model(log))
    return np.where(out.hit, out.ranges, np.nan), np.where(out.hit, out.attributes["label"], 0).astype(np.int32)


@dataclass
class Traversal:
    """Elements met by N rays, in order along each ray.

    Attributes:
        shape: (N, K) int8 index into ``shape_ids`` (-1 = none).
        index: (N, K) int64 element index within its shape (-1 = none).
        t: (N, K) nominal range of the entry point, m (inf = none).
        cos: (N, K) |cos| of the incidence angle at the entry point.
        shape_ids: Mitsuba ids of the scene's shapes.
    """

    shape: np.ndarray
    index: np.ndarray
    t: np.ndarray
    cos: np.ndarray
    shape_ids: list

    def of(self, shape_id: str) -> np.ndarray:
        """(N, K) bool: entries that are elements of shape ``shape_id``."""
        return self.shape == (self.shape_ids.index(shape_id) if shape_id in self.shape_ids else -2)


def trace_elements(
    scene,
    table: ElementTable,
    origins: np.ndarray,
    directions: np.ndarray,
    limit: np.ndarray | float,
    max_elements: int = 16,
) -> Traversal:
    """All elements met along rays up to a per-ray range: the core's tracer (:func:`~mi_lidar.core.trace.trace_rounds`).

    Args:
        scene: loaded scene. table: its element table.
        origins, directions: (N, 3) world rays (unit directions), m.
        limit: (N,) or scalar, m; elements entered beyond it are not listed.
        max_elements: K, most elements listed per ray.
    """
    n = len(origins)
    limit = np.broadcast_to(np.asarray(limit, np.float64), (n,))
    rays = RayBatch(
        origin=mi.Point3f(*(aligned(c) for c in np.asarray(origins, np.float32).T)),
        direction=dr.normalize(mi.Vector3f(*(aligned(c) for c in np.asarray(directions, np.float32).T))),
        beam=dr.zeros(mi.UInt32, n),
        time=dr.zeros(mi.Float, n),
        ray_id=dr.arange(mi.UInt32, n),
    )
    model = SensorModel(max_range=max(float(limit.max(initial=0.0)), 1e-3), max_segments=max_elements)
    rounds = trace_rounds(scene, table, model, rays)
    offsets = np.cumsum([0] + list(table.element_counts))
    shape = np.full((n, max_elements), -1, np.int8)
    index = np.full((n, max_elements), -1, np.int64)
    t = np.full((n, max_elements), np.inf)
    cos = np.zeros((n, max_elements))
    for k, r in enumerate(rounds.rounds):
        rows, r_k = np.asarray(r.ray, np.int64), np.asarray(r.nominal, np.float64)
        found = r_k <= limit[rows]
        rows, elem = rows[found], np.asarray(r.element, np.int64)[found]
        which = np.searchsorted(offsets, elem, side="right") - 1
        shape[rows, k] = which
        index[rows, k] = elem - offsets[which]
        t[rows, k] = r_k[found]
        cos[rows, k] = np.asarray(r.cos_incidence, np.float64)[found]
    return Traversal(shape, index, t, cos, list(table.shape_ids))
