"""Fit a hybrid geometric model to a log: segment, split into blocks, fit elements, count hits.

Steps (thesis fig. 4.7): world points from the log; ground / non-ground by spherical variation;
the x-y plane is cut into square blocks modelled independently (ground surfaces are fitted with a
``margin`` of neighbouring points and keep the triangles whose centroid is inside the block, so
seams stay closed); triangles and ellipsoids get hit probabilities from hits and pass-throughs
along every logged ray with pseudo-count priors; the ground range sigma is a robust (MAD) scale of
the ground residuals (:func:`robust_sigma`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from mi_lidar.core.errors import LogFormatError
from mi_lidar.core.frames import local_origin, shift_poses
from mi_lidar.core.log import Log
from mi_lidar.hybrid.counting import count_hits
from mi_lidar.hybrid.ellipsoids import ClusterParams, fit_ellipsoids
from mi_lidar.hybrid.ground import GroundParams, SurfaceParams, fit_ground_mesh, ground_features
from mi_lidar.hybrid.model import EllipsoidSet, GroundMesh, HybridModel
from mi_lidar.hybrid.simulation import load_model


@dataclass
class FitParams:
    """All fitting parameters (thesis table 4.1).

    Attributes:
        ground: segmentation parameters. surface: ground mesh parameters. clusters: ellipsoids.
        extent: maximum Mahalanobis distance for a hit, sigmas (the ellipsoid extent).
        tri_prior, ell_prior: (hit count prior, miss count prior) pseudo-counts (table 4.1);
            triangles no logged ray crossed get ``tri_prior``'s mean.
        pooled_strength: if > 0, triangles crossed by logged rays use the pooled prior
            ``pooled_strength * (p, 1 - p)``, ``p`` being the hit fraction of all triangle
            crossings, instead of ``tri_prior`` (see :func:`assign_hit_probabilities`).
        max_residual: ground residual still counted as a hit, m.
        pass_sigmas: a triangle is passed only by returns beyond it by more than this many
            standard deviations of the ground's normal residual (see :mod:`.counting`).
        block_size: block side, m. margin: extra points around a block for the ground fit, m.
        max_range: sensor range used for misses, m. max_elements: elements traced per ray.
    """

    ground: GroundParams = field(default_factory=GroundParams)
    surface: SurfaceParams = field(default_factory=SurfaceParams)
    clusters: ClusterParams = field(default_factory=ClusterParams)
    extent: float = 3.5
    tri_prior: tuple[float, float] = (1.0, 2.0)
    ell_prior: tuple[float, float] = (0.0, 1.0)
    pooled_strength: float = 3.0
    max_residual: float = 0.75
    pass_sigmas: float = 3.0
    block_size: float = 50.0
    margin: float = 5.0
    max_range: float = 80.0
    max_elements: int = 16


@dataclass
class FitResult:
    """A fitted model and what produced it.

    Attributes:
        model: the hybrid model.
        points: (M, 3) world hit points, m. ray_index: (M,) flat index of each point's ray in the log.
        is_ground: (M,) bool segmentation. owner: (M,) ellipsoid of each point (-1 = none).
        timings: seconds per stage.
    """

    model: HybridModel
    points: np.ndarray
    ray_index: np.ndarray
    is_ground: np.ndarray
    owner: np.ndarray
    timings: dict


def world_rays(log: Log) -> tuple[np.ndarray, np.ndarray]:
    """(S*H*W, 3) world ray origins (m) and unit directions of every ray of ``log``."""
    s, h, w = log.shape
    rot, trans = log.poses[:, None, None, :3, :3], log.poses[:, None, None, :3, 3]
    d = np.einsum(
        "shwij,shwj->shwi", np.broadcast_to(rot, (s, h, w, 3, 3)), np.broadcast_to(log.directions, (s, h, w, 3))
    )
    o = (
        np.einsum("shwij,shwj->shwi", np.broadcast_to(rot, (s, h, w, 3, 3)), np.broadcast_to(log.origins, (s, h, w, 3)))
        + trans
    )
    return o.reshape(-1, 3), d.reshape(-1, 3)


def block_keys(xy: np.ndarray, size: float, origin: np.ndarray) -> np.ndarray:
    """(N, 2) int64 block coordinates of x-y positions (m) for blocks of side ``size`` (m)."""
    return np.floor((xy - origin) / size).astype(np.int64)


def robust_sigma(residuals: np.ndarray, default: float = 0.05) -> float:
    """Standard deviation of the Gaussian core of ``residuals`` (m): ``1.4826 * median |r - median(r)|``.

    Ground hits are returns within ``max_residual`` (up to about 1 m) of a triangle, so their
    residuals mix the sensor's range noise with the mesh's misfit (grass, object bases, mixed
    pixels at edges). The RMS counts every such return as noise and blurs the whole ground
    (0.10-0.15 m on the experiment's test scenes); the median absolute deviation measures the
    core and is the Gaussian's sigma when the residuals are Gaussian. ``default`` when empty.
    """
    r = np.asarray(residuals, dtype=np.float64)
    if r.size == 0:
        return default
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def hit_probability(hits: np.ndarray, passes: np.ndarray, prior: tuple[float, float]) -> np.ndarray:
    """p_hit = (#hits + a) / (#hits + #pass-throughs + a + b) with prior pseudo-counts (a, b)."""
    a, b = prior
    return (hits + a) / np.maximum(hits + passes + a + b, 1e-12)


def majority(values: np.ndarray, groups: np.ndarray, n: int) -> np.ndarray:
    """(n,) most frequent non-negative value of ``values`` in each group (0 if empty)."""
    if len(values) == 0:
        return np.zeros(n, np.int32)
    vmax = int(values.max()) + 1
    table = np.zeros((n, vmax), np.int64)
    np.add.at(table, (groups, values), 1)
    return table.argmax(axis=1).astype(np.int32)


def assign_hit_probabilities(
    model: HybridModel,
    log: Log,
    owner_of_ray: np.ndarray,
    params: FitParams,
    progress: Callable[[float], None] | None = None,
) -> dict:
    """Set ``p_hit`` of every element and the ground ``range_sigma`` from the log's rays (in place).

    A fine ground mesh gets only a few rays per triangle, and with so few counts the table 4.1
    prior (1, 2), whose mean is 1/3, drags every triangle's p_hit far below the sensor's real
    hit rate (5 hits and 1 pass-through give 0.67 instead of 0.83). With ``pooled_strength > 0``
    the prior of a crossed triangle is centred on the pooled hit fraction of all triangles
    instead (empirical Bayes); triangles no ray crossed keep the thesis prior, so spurious
    triangles stay permeable.

    Args:
        model: model to update.
        log: the log the model was fitted to.
        owner_of_ray: (S*H*W,) ellipsoid owning each ray's return (-1 = none).
        params: priors, residual tests and range limits.
        progress: optional callback receiving the fraction of rays counted.

    Returns:
        Summary counts (hits and pass-throughs per kind, grazing crossings, ground sigma along
        the ray and along the normal, m).
    """
    origins, directions = world_rays(log)
    measured = np.where(log.hit, log.ranges, np.nan).ravel()
    nf, ne = len(model.ground), len(model.ellipsoids)
    c = count_hits(
        load_model(model),
        origins,
        directions,
        measured,
        owner_of_ray,
        nf,
        ne,
        params.max_residual,
        params.pass_sigmas,
        params.max_range,
        params.max_elements,
        progress=progress,
    )
    sigma = robust_sigma(c.residuals)
    crossings = c.tri_hits.sum() + c.tri_pass.sum()
    pooled = float(c.tri_hits.sum() / crossings) if crossings else 1.0
    prior = (params.pooled_strength * pooled, params.pooled_strength * (1 - pooled))
    crossed = (c.tri_hits + c.tri_pass) > 0
    model.ground.p_hit = np.where(
        crossed & (params.pooled_strength > 0),
        hit_probability(c.tri_hits, c.tri_pass, prior),
        hit_probability(c.tri_hits, c.tri_pass, params.tri_prior),
    )
    model.ground.range_sigma = np.full(nf, sigma)
    model.ellipsoids.p_hit = hit_probability(c.ell_hits, c.ell_pass, params.ell_prior)
    return {
        "triangle_hits": float(c.tri_hits.sum()),
        "triangle_passes": float(c.tri_pass.sum()),
        "grazing_crossings": c.grazing,
        "ellipsoid_hits": float(c.ell_hits.sum()),
        "ellipsoid_passes": float(c.ell_pass.sum()),
        "ground_sigma": sigma,
        "ground_sigma_normal": c.sigma_normal,
        "pooled_triangle_p_hit": pooled,
        "mean_triangle_p_hit": float(model.ground.p_hit.mean()) if nf else float("nan"),
    }


def fit_model(
    log: Log,
    params: FitParams | None = None,
    progress: Callable[[str, float], None] | None = None,
    ground_only: bool = False,
) -> FitResult:
    """Fit the hybrid geometric model of the scene seen by ``log``.

    Args:
        log: a log (world-frame points come from its poses).
        params: fitting parameters (defaults: :class:`FitParams`).
        progress: optional callback ``progress(stage, fraction_done)``.
        ground_only: fit only the ground triangles (e.g. the ground of a composed test scene).

    Returns:
        The :class:`FitResult`; its points and model are in the model's local frame (``model.origin``
        is zero unless the returns lie beyond :data:`~mi_lidar.core.frames.NEAR_M`). If the log has
        ``label`` / ``instance`` attributes, element labels and instances are the majority of their
        points; triangles get label ``ground``.

    Raises:
        LogFormatError: the log's returns give neither a ground triangle nor an ellipsoid (too few of them).
    """
    params = params or FitParams()
    report = progress or (lambda stage, fraction: None)
    timings = {}
    t0 = time.perf_counter()
    ray_index = np.flatnonzero(log.hit.ravel())
    frame = local_origin(log.points_world().reshape(-1, 3)[ray_index])
    if np.any(frame):  # georeferenced returns: fit in the local frame (float32 meshes and Mitsuba keep mm there)
        log = replace(log, poses=shift_poses(log.poses, frame))
    points = log.points_world().reshape(-1, 3)[ray_index]
    timings["points"] = time.perf_counter() - t0

    report("ground segmentation", 0.0)
    t0 = time.perf_counter()
    is_ground = ground_features(points, params.ground) < params.ground.phi_thresh
    timings["segmentation"] = time.perf_counter() - t0

    origin = points[:, :2].min(axis=0) if len(points) else np.zeros(2)
    keys = block_keys(points[:, :2], params.block_size, origin)
    blocks = np.unique(keys, axis=0)
    grounds, ells = [], []
    owner = np.full(len(points), -1, np.int64)
    n_ell = 0
    timings["ground_mesh"] = timings["ellipsoids"] = 0.0
    ground_pts = points[is_ground]
    for b, key in enumerate(blocks):
        report("blocks", b / max(len(blocks), 1))
        lo = origin + key * params.block_size
        hi = lo + params.block_size
        t0 = time.perf_counter()
        near = np.all((ground_pts[:, :2] >= lo - params.margin) & (ground_pts[:, :2] < hi + params.margin), axis=1)
        mesh = fit_ground_mesh(ground_pts[near], params.surface, keep_xy=(lo[0], lo[1], hi[0], hi[1]))
        mesh.block[:] = b
        grounds.append(mesh)
        timings["ground_mesh"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        inside = np.nonzero(~is_ground & np.all(keys == key, axis=1) & (not ground_only))[0]
        ell, member = fit_ellipsoids(points[inside], params.clusters)
        ell.block[:] = b
        owner[inside] = np.where(member >= 0, member + n_ell, -1)
        n_ell += len(ell)
        ells.append(ell)
        timings["ellipsoids"] += time.perf_counter() - t0
    model = HybridModel(
        GroundMesh.concat(grounds),
        EllipsoidSet.concat(ells),
        params.extent,
        info={"n_blocks": int(len(blocks)), "block_size": params.block_size},
        origin=frame,
    )
    if len(model.ground) == 0 and len(model.ellipsoids) == 0:
        raise LogFormatError(
            f"{log.source or 'the log'}: the fit found neither ground nor vegetation in the log's {len(points)} "
            "returns; give a 3D log with returns from the ground (e.g. `mi-lidar synth-world --out train.npz`)"
        )
    if "label" in log.attributes and len(model.ellipsoids):
        labels = log.attributes["label"].ravel()[ray_index]
        inst = log.attributes["instance"].ravel()[ray_index] if "instance" in log.attributes else np.zeros_like(labels)
        sel = owner >= 0
        model.ellipsoids.label = majority(labels[sel], owner[sel], len(model.ellipsoids))
        model.ellipsoids.instance = majority(np.maximum(inst[sel], 0), owner[sel], len(model.ellipsoids))
    model.ground.label[:] = 1

    report("hit probabilities", 0.0)
    t0 = time.perf_counter()
    owner_of_ray = np.full(log.n_rays, -1, np.int64)
    owner_of_ray[ray_index] = owner
    model.info.update(
        assign_hit_probabilities(
            model, log, owner_of_ray, params, lambda fraction: report("hit probabilities", fraction)
        )
    )
    timings["hit_probabilities"] = time.perf_counter() - t0
    report("done", 1.0)
    return FitResult(model, points, ray_index, is_ground, owner, timings)
