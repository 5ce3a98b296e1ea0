"""The loop on real measured data: the Intel lab CARMEN log with leave-out maps.

Protocol (fixed so that the numbers compare with reference models measured on the same log):

* test scans are every ``test_every``-th scan (0, 5, 10, ...);
* the map of a scan is built from every scan except those within ``radius`` m **and**
  ``window`` s of it (:func:`exclusion`); calibration scans (``2, 7, 12, ...``) also leave every
  test scan out of their maps, so no test beam reaches a fitted number;
* each beam is scored by its log-likelihood (nats) with ranges in 1 cm bins
  (:meth:`SensorModel.log_likelihood` with ``resolution=0.01``); SICK max-range readings are misses.

Maps are counts on a 5 cm grid (:mod:`mi_lidar.loop.occupancy`); the leave-out map of a scan is
the total minus the contributions of its excluded scans, exact and cheap. Each scored scan gets
its own map as one *layer* of a single Mitsuba scene: layer ``j`` sits at height ``j * LAYER`` m
and holds only the map cells within two cells of that scan's beams (up to 1 m past a return:
elements farther behind it add less than ``exp(-50)`` to its likelihood), so one trace and one
likelihood call score every scan against its own map. Two element kinds:

* :func:`box_elements`: occupied cells (more hits than pass-throughs) as opaque vertical boxes,
  for the ideal ray cast and classic beam baselines;
* :func:`ellipsoid_elements`: every cell with a hit as a permeable Gaussian ellipsoid (mean and
  covariance of its end points plus ``s_min^2 I``, ``z`` scale ``s_z``) whose hit probability is
  the counting estimate ``(hits + a) / (hits + passes + a + b)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..calibration.scene_dicts import EllipsoidElements, MeshElements, scene_dict
from ..effects.base import Effect
from ..elements import ElementTable
from ..log import Log
from ..sensor_model import SensorModel
from .fit import Problem, fit_effects
from .occupancy import CountMap, Grid, count_scans, planar_rays, ray_cells
from .rays import LogRays

LAYER = 4.0  # m: height between the stacked per-scan maps
BOX_HALF_HEIGHT = 0.5  # m
RESOLUTION = 0.01  # m: range bin of the score
BATCH = 1 << 18  # rays scored at once


def exclusion(log: Log, scan: int, radius: float = 1.0, window: float = 30.0) -> np.ndarray:
    """Scans whose pose is within ``radius`` m and whose time is within ``window`` s of ``scan`` (itself included)."""
    xy = log.poses[:, :2, 3]
    t = log.times[:, 0, 0]
    near = np.hypot(*(xy - xy[scan]).T) <= radius
    recent = np.abs(t - t[scan]) <= window
    return np.flatnonzero(near & recent)


def stacked_log(log: Log, scans: np.ndarray) -> Log:
    """The scans of ``log`` with scan ``j`` lifted to height ``j * LAYER`` m (its map layer)."""
    poses = log.poses[scans].copy()
    poses[:, 2, 3] = np.arange(len(scans)) * LAYER
    return Log(poses=poses, directions=log.directions, ranges=log.ranges[scans], hit=log.hit[scans],
               times=log.times[scans], sensor=dict(log.sensor))


@dataclass
class EllipsoidPrior:
    """Hyperparameters of the permeable ellipsoid map.

    Attributes:
        a, b: Beta prior of the counting estimate ``(hits + a) / (hits + passes + a + b)``.
        s_min: added to each cell's end-point spread in quadrature, m.
        s_max: cap of the in-plane scales, m.
        s_z: vertical scale, m (the planar beams run through the middle).
    """

    a: float = 0.5
    b: float = 0.5
    s_min: float = 0.01
    s_max: float = 0.05
    s_z: float = 0.5


@dataclass
class Layers:
    """Per-scan leave-out maps of a set of scored scans, as cells of the count grid.

    Attributes:
        scans: (L,) scored scans (layer ``j`` is ``scans[j]``).
        cells: per layer, the flat grid cells within reach of the scan's beams that had a hit.
        maps: per layer, the leave-out :data:`~mi_lidar.loop.occupancy.MOMENTS` of those cells.
    """

    scans: np.ndarray
    cells: list = field(default_factory=list)
    maps: list = field(default_factory=list)


class IntelData:
    """The Intel log, its 5 cm count map, and the test / calibration splits of the protocol.

    Args:
        log: the planar log (:func:`mi_lidar.io.carmen.read_carmen`).
        cell: grid cell, m.
        test_every: every ``test_every``-th scan is a test scan.
        radius, window: the leave-out neighbourhood (m, s).
    """

    def __init__(self, log: Log, cell: float = 0.05, test_every: int = 5, radius: float = 1.0, window: float = 30.0):
        self.log, self.radius, self.window = log, radius, window
        origin, direction, r, hit = planar_rays(log, np.arange(log.shape[0]))
        ends = (origin + r[:, None] * direction)[hit]
        lo, hi = np.percentile(ends, [0.05, 99.95], axis=0)
        inside = np.all((ends >= lo) & (ends <= hi), axis=1)
        self.grid = Grid.around(np.concatenate([ends[inside], log.poses[:, :2, 3]]), cell)
        self.counts = count_scans(log, self.grid)
        self.map = CountMap(self.counts)
        self.test = np.arange(0, log.shape[0], test_every)
        self.train = np.arange(2, log.shape[0], test_every)

    def excluded(self, scan: int, calibration: bool) -> np.ndarray:
        """Scans left out of the map of ``scan``; calibration maps also leave out every test scan."""
        out = exclusion(self.log, scan, self.radius, self.window)
        return np.union1d(out, self.test) if calibration else out

    def layers(self, scans: np.ndarray, calibration: bool, progress=None) -> Layers:
        """The leave-out map cells of each of ``scans`` (see the module docstring)."""
        layers = Layers(scans=np.asarray(scans))
        for j, scan in enumerate(layers.scans):
            moments = self.map.leave_out(self.excluded(int(scan), calibration))
            origin, direction, r, hit = planar_rays(self.log, np.array([scan]))
            reach = np.where(hit, r + 1.0, self.grid.exit_distance(origin, direction))
            _, cells = ray_cells(self.grid, origin, direction, reach, self.grid.cell / 2, dilate=2)
            cells = np.unique(cells)
            cells = cells[moments["n_hit"][cells] > 0]
            layers.cells.append(cells)
            layers.maps.append({k: v[cells] for k, v in moments.items()})
            if progress is not None:
                progress(j + 1, len(layers.scans))
        return layers


def box_elements(grid: Grid, layers: Layers, log: Log | None = None, ring_radius: float = 81.83) -> MeshElements:
    """Occupied cells (more hits than pass-throughs) of every layer as opaque vertical boxes (8 triangles each).

    With ``log`` each layer also gets a *max-range ring*: 360 vertical quads at ``ring_radius`` m
    around its scan's position with hit probability 0.5, so that a beam whose ray cast meets no
    box expects a reading at the maximum range (half of them reported as misses), as an ideal
    ray cast that returns the maximum range for empty beams does.
    """
    corners, z = [], []
    for j, (cells, m) in enumerate(zip(layers.cells, layers.maps)):
        occupied = cells[m["n_hit"] > m["n_pass"]]
        corners.append(grid.center(occupied))
        z.append(np.full(len(occupied), j * LAYER))
    center, z = np.concatenate(corners), np.concatenate(z)
    h, d = BOX_HALF_HEIGHT, grid.cell / 2
    square = np.array([[-d, -d], [d, -d], [d, d], [-d, d]])
    bottom = np.concatenate([center[:, None, :] + square[None], (z[:, None] - h)[..., None].repeat(4, 1)], -1)
    top = bottom.copy()
    top[..., 2] += 2 * h
    vertices = np.concatenate([bottom, top], axis=1).reshape(-1, 3)  # 8 per box: bottom 0-3, top 4-7
    sides = np.array([[0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    faces = (np.arange(len(center))[:, None, None] * 8 + sides[None]).reshape(-1, 3)
    p_hit = np.ones(len(faces))
    if log is not None:
        angle = np.linspace(0, 2 * np.pi, 361)[:-1]
        circle = ring_radius * np.stack([np.cos(angle), np.sin(angle)], -1)
        ring_v, ring_f = [], []
        for j, scan in enumerate(layers.scans):
            xy = log.poses[scan, :2, 3] + circle
            base = len(vertices) + j * 720
            ring_v.append(np.concatenate([np.c_[xy, np.full(360, j * LAYER - h)], np.c_[xy, np.full(360, j * LAYER + h)]]))
            a, b = np.arange(360), (np.arange(360) + 1) % 360
            ring_f.append(base + np.concatenate([np.stack([a, b, b + 360], -1), np.stack([a, b + 360, a + 360], -1)]))
        vertices = np.concatenate([vertices] + ring_v)
        faces = np.concatenate([faces] + ring_f)
        p_hit = np.concatenate([p_hit, np.full(len(faces) - len(p_hit), 0.5)])
    return MeshElements(vertices=vertices, faces=faces, p_hit=p_hit, label=np.zeros(len(faces)))


def ellipsoid_elements(grid: Grid, layers: Layers, prior: EllipsoidPrior) -> EllipsoidElements:
    """Every cell with a hit, per layer, as a permeable Gaussian ellipsoid (see the module docstring)."""
    centers, scales, quats, p_hit = [], [], [], []
    for j, (cells, m) in enumerate(zip(layers.cells, layers.maps)):
        n = m["n_hit"]
        mx, my = m["sx"] / n, m["sy"] / n
        cxx = np.maximum(m["sxx"] / n - mx * mx, 0.0) + prior.s_min ** 2
        cyy = np.maximum(m["syy"] / n - my * my, 0.0) + prior.s_min ** 2
        cxy = m["sxy"] / n - mx * my
        # ---------------- Eigen-decomposition of the 2x2 covariance ----------------
        half_trace, diff = 0.5 * (cxx + cyy), 0.5 * (cxx - cyy)
        root = np.sqrt(diff * diff + cxy * cxy)
        major, minor = half_trace + root, np.maximum(half_trace - root, prior.s_min ** 2)
        angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
        centers.append(np.stack([grid.center(cells)[:, 0] + mx, grid.center(cells)[:, 1] + my, np.full(len(cells), j * LAYER)], -1))
        scales.append(np.stack([np.minimum(np.sqrt(major), prior.s_max), np.minimum(np.sqrt(minor), prior.s_max),
                                np.full(len(cells), prior.s_z)], -1))
        quats.append(np.stack([np.zeros_like(angle), np.zeros_like(angle), np.sin(angle / 2), np.cos(angle / 2)], -1))
        p_hit.append((n + prior.a) / (n + m["n_pass"] + prior.a + prior.b))
    return EllipsoidElements(centers=np.concatenate(centers), scales=np.concatenate(scales),
                             quaternions=np.concatenate(quats), p_hit=np.concatenate(p_hit),
                             label=np.zeros(sum(len(c) for c in layers.cells)))


@dataclass
class Scored:
    """A stacked scene with its scored rays: traced once, scored with :meth:`SensorModel.log_likelihood`.

    Attributes:
        scene: the loaded scene of every layer's elements.
        table: its element table.
        rays: the layers' scans as rays (layer ``j`` is scan ``j`` of the stacked log).
        n_elements: elements in the scene.
    """

    scene: object
    table: ElementTable
    rays: LogRays
    n_elements: int
    _records: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, log: Log, layers: Layers, elements) -> "Scored":
        """Load ``elements`` (all layers) as one scene and attach the layers' scans as rays."""
        scene = mi.load_dict(scene_dict({"map": elements}))
        n = len(elements.faces) if isinstance(elements, MeshElements) else len(elements.centers)
        return cls(scene=scene, table=ElementTable.from_scene(scene), rays=LogRays.from_log(stacked_log(log, layers.scans)),
                   n_elements=n)

    def per_beam(self, model: SensorModel) -> np.ndarray:
        """(N,) log-likelihood per beam (nats, 1 cm range bins) under ``model``; not floored."""
        out = []
        for first in range(0, self.rays.n, BATCH):
            index = np.arange(first, min(first + BATCH, self.rays.n))
            batch, measured, hit = self.rays.batch(index)
            key = (first, model.max_segments, model.max_range)
            if key not in self._records:
                self._records[key] = model.trace_segments(self.scene, self.table, batch)
            with dr.suspend_grad():
                ll = model.log_likelihood(self.table, batch, self._records[key], measured, hit, resolution=RESOLUTION)
            out.append(np.asarray(ll, dtype=np.float64))
        return np.concatenate(out)

    def nll(self, model: SensorModel) -> float:
        """Mean negative log-likelihood per beam (nats) under ``model``."""
        return float(-np.mean(self.per_beam(model)))

    def fit(self, model: SensorModel, effects: list[Effect], steps: int = 150) -> None:
        """Fit ``effects`` (members of ``model.effects``) on these rays by maximum likelihood (:func:`fit_effects`)."""
        problem = Problem.build(self.scene, self.rays, np.arange(self.rays.n), resolution=RESOLUTION)
        fit_effects(model, problem, effects, steps=steps)


@dataclass
class Step:
    """One row of a development path.

    Attributes:
        model: what was scored.
        added: the effect or change this step adds.
        nll: mean negative log-likelihood per test beam, nats.
        train_nll: the same on the calibration beams, nats.
        fitted: fitted parameters, ``{"effect.param": value}``.
    """

    model: str
    added: str
    nll: float
    train_nll: float
    fitted: dict


def _describe(effects: list[Effect]) -> dict:
    return {f"{e.name}.{k}": float(np.asarray(v)[0]) for e in effects for k, v in e.params.items()}


def _fit_and_score(train: Scored, test: Scored, model: SensorModel, fit: list[Effect], steps: int) -> tuple[float, float]:
    if fit:
        train.fit(model, fit, steps=steps)
    return test.nll(model), train.nll(model)


def intel_development_path(data: IntelData, n_test: int | None = None, n_train: int | None = None, steps: int = 150,
                           priors: list[EllipsoidPrior] | None = None, progress=None) -> list[Step]:
    """Baselines, then the permeable map with effects added one by one; every fit on calibration scans only.

    Args:
        data: the log and its count map.
        n_test, n_train: use the first this many test / calibration scans (all when None).
        steps: Adam steps per fit.
        priors: candidate ellipsoid priors for the last step (chosen by calibration NLL).
        progress: optional callable ``progress(message)``.

    Returns:
        The development path: one :class:`Step` per row.
    """
    from ..effects import make_effect

    say = progress or (lambda message: None)
    test_layers = data.layers(data.test[:n_test], calibration=False)
    train_layers = data.layers(data.train[:n_train], calibration=True)
    say(f"maps: {len(test_layers.scans)} test and {len(train_layers.scans)} calibration layers")
    rows = []

    # ---------------- Baselines: opaque boxes of the occupied cells ----------------
    box_test = Scored.build(data.log, test_layers, box_elements(data.grid, test_layers, data.log))
    box_train = Scored.build(data.log, train_layers, box_elements(data.grid, train_layers, data.log))
    noise, drop = make_effect("range_noise", sigma0=0.2), make_effect("random_dropout", p_drop=0.02)
    model = SensorModel(range_sigma=1e-3, max_range=90.0, max_segments=3, effects=[noise, drop])
    best = None
    for sigma in np.geomspace(0.01, 2.0, 24):  # exact maximum likelihood: no floor, so a grid
        for p_drop in (0.005, 0.01, 0.02, 0.04, 0.08):
            noise.params["sigma0"], drop.params["p_drop"] = mi.Float(sigma), mi.Float(p_drop)
            value = box_train.nll(model)
            best = min(best or (np.inf, 0, 0), (value, sigma, p_drop))
    noise.params["sigma0"], drop.params["p_drop"] = mi.Float(best[1]), mi.Float(best[2])
    nll, train_nll = box_test.nll(model), best[0]
    rows.append(Step("ideal ray cast, 5 cm occupancy boxes", "one Gaussian sigma + miss probability", nll, train_nll,
                     _describe(model.effects)))
    say(f"ideal ray cast: {nll:.3f}")
    outliers = make_effect("outliers", p_near=0.05, near_scale=2.0, p_uniform=0.01, uniform_max=81.83)
    model.effects = [outliers, noise, drop]
    nll, train_nll = _fit_and_score(box_train, box_test, model, model.effects, steps)
    rows.append(Step("classic beam model on the boxes", "short (near) + random + max-range components", nll, train_nll,
                     _describe(model.effects)))
    say(f"classic beam: {nll:.3f}")

    # ---------------- Ours: permeable ellipsoids with counting hit probabilities ----------
    priors = priors or [EllipsoidPrior()]
    prior = priors[0]
    ours_test = Scored.build(data.log, test_layers, ellipsoid_elements(data.grid, test_layers, prior))
    ours_train = Scored.build(data.log, train_layers, ellipsoid_elements(data.grid, train_layers, prior))
    model = SensorModel(range_sigma=0.01, max_range=81.0, max_segments=32, effects=[])
    nll, train_nll = _fit_and_score(ours_train, ours_test, model, [], steps)
    rows.append(Step("permeable ellipsoid map, counting p_hit", "(map only)", nll, train_nll, {}))
    say(f"permeable map: {nll:.3f}")
    added = [
        ("outliers", make_effect("outliers", p_near=0.02, near_scale=2.0, p_uniform=0.005, uniform_max=81.83)),
        ("range_noise (physics law)", make_effect("range_noise", law="physics", sigma0=0.005, k=1e-5)),
        ("incidence_dropout", make_effect("incidence_dropout", gamma=0.3)),
        ("range_dropout", make_effect("range_dropout", rate=0.05, power=2.0)),
    ]
    for label, effect in added:
        model.effects = model.effects + [effect]
        nll, train_nll = _fit_and_score(ours_train, ours_test, model, model.effects, steps)
        rows.append(Step("permeable ellipsoid map", f"+ {label}", nll, train_nll, _describe(model.effects)))
        say(f"+ {label}: {nll:.3f}")
    return rows


# ======================================================================= Ouster frame
def range_image_mesh(log: Log, columns: np.ndarray, max_ratio: float = 1.1) -> MeshElements:
    """Triangles between neighbouring returns of a range image restricted to ``columns``.

    Args:
        log: a one-scan log (``S = 1``), rows are beams and columns azimuth bins.
        columns: ascending columns whose returns become vertices; neighbours are consecutive
            entries (the last wraps to the first, as a spinning sensor's image does).
        max_ratio: a triangle is kept when the largest of its three ranges is at most this
            times the smallest (no faces across depth discontinuities).

    Returns:
        Opaque faces (``p_hit`` 1) in the world frame, default range sigma.
    """
    scan = 0
    h = log.shape[1]
    origins = log.origins[0 if log.origins.shape[0] == 1 else scan]
    directions = log.directions[0 if log.directions.shape[0] == 1 else scan]
    r = log.ranges[scan][:, columns]
    hit = log.hit[scan][:, columns]
    points = origins[:, columns] + np.nan_to_num(r)[..., None] * directions[:, columns]
    pose = log.poses[scan]
    points = points.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]
    w = len(columns)
    vid = np.arange(h * w).reshape(h, w)
    u, v = np.meshgrid(np.arange(h - 1), np.arange(w), indexing="ij")
    right = (v + 1) % w
    quads = [(vid[u, v], vid[u + 1, v], vid[u, right]), (vid[u + 1, v], vid[u + 1, right], vid[u, right])]
    faces = []
    flat_r, flat_hit = np.nan_to_num(r).ravel(), hit.ravel()
    for tri in quads:
        tri = np.stack([t.ravel() for t in tri], -1)
        ok = flat_hit[tri].all(axis=1)
        rr = flat_r[tri]
        ok &= rr.max(axis=1) <= max_ratio * np.maximum(rr.min(axis=1), 1e-6)
        faces.append(tri[ok])
    faces = np.concatenate(faces)
    return MeshElements(vertices=points, faces=faces, p_hit=np.ones(len(faces)), label=np.zeros(len(faces)))


def ouster_development_path(log: Log, steps: int = 150, progress=None) -> list[Step]:
    """Mesh from columns ``0 mod 4``, calibration on columns ``2 mod 4``, test on odd columns.

    Every step adds one effect to the mesh model and fits all effects on the calibration rays;
    the test score is the mean negative log-likelihood per odd-column ray (nats, 1 cm bins).
    """
    from ..effects import make_effect

    say = progress or (lambda message: None)
    w = log.shape[2]
    mesh = range_image_mesh(log, np.arange(0, w, 4))
    scene = mi.load_dict(scene_dict({"map": mesh}))
    table = ElementTable.from_scene(scene)
    rays = LogRays.from_log(log)
    test = Scored(scene=scene, table=table, rays=_subset(rays, rays.column % 2 == 1), n_elements=len(mesh.faces))
    train = Scored(scene=scene, table=table, rays=_subset(rays, rays.column % 4 == 2), n_elements=len(mesh.faces))
    say(f"mesh: {len(mesh.faces)} faces from {w // 4} columns; {train.rays.n} calibration and {test.rays.n} test rays")
    model = SensorModel(range_sigma=0.01, max_range=120.0, max_segments=4, effects=[])
    rows = []
    ll = test.per_beam(model)
    rows.append(Step("range-image mesh, opaque, sigma 1 cm", "(mesh only)", float(-np.mean(ll)),
                     train.nll(model), {"unexplained test rays": int(np.sum(~np.isfinite(ll)))}))
    added = [
        ("outliers", make_effect("outliers", p_near=0.02, near_scale=2.0, p_uniform=0.005, uniform_max=120.0)),
        ("range_noise (proportional)", make_effect("range_noise", law="proportional", sigma0=0.02, k=0.002)),
        ("random_dropout", make_effect("random_dropout", p_drop=0.02)),
        ("incidence_dropout", make_effect("incidence_dropout", gamma=0.3)),
        ("range_dropout", make_effect("range_dropout", rate=0.05, power=2.0)),
    ]
    for label, effect in added:
        model.effects = model.effects + [effect]
        nll, train_nll = _fit_and_score(train, test, model, model.effects, steps)
        rows.append(Step("range-image mesh", f"+ {label}", nll, train_nll, _describe(model.effects)))
        say(f"+ {label}: {nll:.3f}")
    return rows


def _subset(rays: LogRays, keep: np.ndarray) -> LogRays:
    """The rays of ``rays`` where ``keep`` holds (ray ids stay the log's flat indices)."""
    index = np.flatnonzero(keep)
    return _IndexedRays(log=rays.log, scan=rays.scan[index], beam=rays.beam[index], column=rays.column[index],
                        time=rays.time[index], measured=rays.measured[index], hit=rays.hit[index], ids=index)


@dataclass
class _IndexedRays(LogRays):
    """A subset of a log's rays that keeps the log's flat ray ids."""

    ids: np.ndarray = None

    def batch(self, index: np.ndarray | None = None):
        index = np.arange(self.n) if index is None else np.asarray(index)
        full = LogRays(log=self.log, scan=self.scan, beam=self.beam, column=self.column, time=self.time,
                       measured=self.measured, hit=self.hit)
        rays, measured, hit = full.batch(index)
        rays.ray_id = mi.UInt32(self.ids[index].astype(np.uint32))
        return rays, measured, hit
