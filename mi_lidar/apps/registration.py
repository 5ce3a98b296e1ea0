"""Scan-to-map registration in an EKF along the trajectory (thesis 3.5.2).

The filter runs along every scan of the log, stretch after stretch (about 20 m of travel each; each
stretch starts from a noisy pose, so a filter that loses track loses one stretch, not the rest of the
log): it predicts each state from the previous estimate by the noisy odometry motion
(:func:`~mi_lidar.apps.scans.noisy_runs`; the filter's motion noise is the odometry's,
:func:`~mi_lidar.apps.scans.motion_sigma`), registers the scan to the
state's leave-out map by point-to-line ICP (:func:`icp_runs`) from the prediction, and fuses the
registered pose as a measurement of the pose (EKF update, :func:`_update`). A registration whose inlier
share is below the gate is rejected (prediction only). The runs of one evaluation are filtered side by
side (one KD-tree query per ICP iteration for all of them); run ``r`` has the same noise on every
dataset and sees a simulator's ``r``-th sampled scans.

========================  ============================================================  ======
alpha                     meaning                                                       unit
========================  ============================================================  ======
``max_distance``          a scan point farther than this from the map is an outlier      m
``iterations``            ICP refining iterations (it may converge in fewer)             -
``min_inliers``           reject a registration with a smaller share of inliers         -
========================  ============================================================  ======

``J``: the mean position error of the filter (m) over states and runs, against the SLAM-corrected
poses, each state's error capped at :data:`~mi_lidar.apps.scans.CAP` m (a lost filter counts as lost);
runs are added while its standard error exceeds ``target_se`` (up to ``max_runs``).
Also reported: the mean heading error (deg), the mean ICP iterations run (the thesis's convergence
time), the share of rejected registrations and the divergence rate (error > 1 m).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from mi_lidar.apps.risk import Parameter
from mi_lidar.apps.scans import (
    CAP,
    REACH,
    START_NOISE,
    PlanarStates,
    Tracker,
    compose,
    motion_sigma,
    noisy_runs,
    run_ranges,
    stretch_mask,
    stretches,
    tracker_metrics,
    wrap,
)

POINT_SIGMA = 0.05  # m: the filter's noise of one point-to-line distance (the map's 5 cm cells)
MEASUREMENT_FLOOR = (0.01, np.radians(0.2))  # least noise of a registered pose: position (m), heading (rad)


@dataclass
class MapIndex:
    """Map points with their line normals and a KD-tree.

    Attributes:
        points: (M, 2) map points (m).
        normals: (M, 2) unit normals of the line through each point's neighbours (PCA of ``k`` nearest).
        tree: KD-tree of ``points``.
    """

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree

    @classmethod
    def build(cls, points: np.ndarray, k: int = 8) -> MapIndex:
        tree = cKDTree(points)
        _, near = tree.query(points, k=min(k, len(points)))
        nb = points[near] - points[near].mean(axis=1, keepdims=True)
        cxx, cyy, cxy = (nb[..., 0] ** 2).sum(1), (nb[..., 1] ** 2).sum(1), (nb[..., 0] * nb[..., 1]).sum(1)
        angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # direction of the major axis
        return cls(points=points, normals=np.stack([-np.sin(angle), np.cos(angle)], axis=1), tree=tree)


@dataclass
class Registration:
    """Result of :func:`icp_runs` for R runs.

    Attributes:
        pose: (R, 3) the registered poses.
        share: (R,) share of each scan's points within ``max_distance`` of the map at that pose.
        iterations: (R,) iterations run.
        information: (R, 3, 3) ``sum J^T J`` of the point-to-line residuals at the pose (1/m^2 units per
            pose coordinate): small along directions the map does not constrain (a corridor's axis).
    """

    pose: np.ndarray
    share: np.ndarray
    iterations: np.ndarray
    information: np.ndarray


def _pairs(points: np.ndarray, valid: np.ndarray, index: MapIndex, pose: np.ndarray, max_distance: float):
    """Point-to-line pairs of R scans at R poses: residuals (R, n), Jacobians (R, n, 3) (0 off the pairs), pairs (R, n).

    ``points`` (R, n, 2) in the laser frame, ``valid`` (R, n) marks real points; a point pairs with its
    nearest map point within ``max_distance``.
    """
    c, s = np.cos(pose[:, 2:3]), np.sin(pose[:, 2:3])
    world = np.stack(
        [pose[:, :1] + c * points[..., 0] - s * points[..., 1], pose[:, 1:2] + s * points[..., 0] + c * points[..., 1]],
        axis=-1,
    )
    distance, nearest = index.tree.query(world.reshape(-1, 2), distance_upper_bound=max_distance)
    paired = valid & np.isfinite(distance).reshape(valid.shape)
    nearest = np.where(paired, nearest.reshape(valid.shape), 0)
    n = index.normals[nearest]
    residual = np.where(paired, np.sum(n * (world - index.points[nearest]), axis=-1), 0.0)
    arm = world - pose[:, None, :2]
    jacobian = np.stack([n[..., 0], n[..., 1], n[..., 1] * arm[..., 0] - n[..., 0] * arm[..., 1]], axis=-1)
    return residual, jacobian * paired[..., None], paired


def icp_runs(
    points: np.ndarray,
    valid: np.ndarray,
    index: MapIndex,
    pose: np.ndarray,
    max_distance: float,
    iterations: int,
    tolerance: float = 1e-4,
) -> Registration:
    """Point-to-line ICP of R scans to one map, each from its own pose (R, 3).

    Each iteration pairs every point (``points`` (R, n, 2) in the laser frame where ``valid`` (R, n))
    with its nearest map point within ``max_distance`` and takes one Gauss-Newton step on the sum of
    squared point-to-line distances; a scan stops after ``iterations``, when fewer than 3 pairs remain,
    or when a step moves less than ``tolerance`` (m, and rad).
    """
    pose = np.array(pose, np.float64)
    run = np.zeros(len(pose), np.int64)
    active = np.arange(len(pose))
    for _ in range(iterations):
        if not active.size:
            break
        run[active] += 1
        residual, jacobian, paired = _pairs(points[active], valid[active], index, pose[active], max_distance)
        hessian = np.einsum("rni,rnj->rij", jacobian, jacobian) + 1e-6 * np.eye(3)
        step = np.linalg.solve(hessian, -np.einsum("rni,rn->ri", jacobian, residual)[..., None])[..., 0]
        enough = paired.sum(axis=1) >= 3
        step[~enough] = 0.0
        pose[active] += step
        pose[active, 2] = wrap(pose[active, 2])
        small = (np.hypot(step[:, 0], step[:, 1]) < tolerance) & (np.abs(step[:, 2]) < tolerance)
        active = active[enough & ~small]
    _, jacobian, paired = _pairs(points, valid, index, pose, max_distance)
    share = paired.sum(axis=1) / np.maximum(valid.sum(axis=1), 1)
    return Registration(
        pose=pose, share=share, iterations=run, information=np.einsum("rni,rnj->rij", jacobian, jacobian)
    )


def icp(points: np.ndarray, index: MapIndex, pose: np.ndarray, max_distance: float, iterations: int) -> Registration:
    """ICP of one scan's laser-frame ``points`` (n, 2) from ``pose`` (3,) (:func:`icp_runs` with R = 1)."""
    one = icp_runs(
        points[None], np.ones((1, len(points)), bool), index, np.asarray(pose)[None], max_distance, iterations
    )
    return Registration(
        pose=one.pose[0], share=one.share[0], iterations=one.iterations[0], information=one.information[0]
    )


def scan_batch(ranges: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Laser-frame points (R, N, 2) of R scans' ranges (R, N) (m), and which are returns closer than :data:`REACH`."""
    valid = np.isfinite(ranges) & (ranges > 0) & (ranges < REACH)
    r = np.where(valid, ranges, 0.0)
    return np.stack([r * np.cos(angles), r * np.sin(angles)], axis=-1), valid


def _predict(mean: np.ndarray, cov: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """EKF motion update of R filters (means (R, 3), covariances (R, 3, 3)) by robot-frame motions ``u`` (R, 3)."""
    c, s = np.cos(mean[:, 2]), np.sin(mean[:, 2])
    zero, one = np.zeros_like(c), np.ones_like(c)
    f = np.stack(
        [
            np.stack([one, zero, -s * u[:, 0] - c * u[:, 1]], -1),
            np.stack([zero, one, c * u[:, 0] - s * u[:, 1]], -1),
            np.stack([zero, zero, one], -1),
        ],
        axis=1,
    )
    w = np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], axis=1)
    q = motion_sigma(u) ** 2
    noise = np.einsum("rij,rj,rkj->rik", w, q, w)
    return compose(mean, u), f @ cov @ np.swapaxes(f, 1, 2) + noise


def _update(mean: np.ndarray, cov: np.ndarray, registered: Registration) -> tuple[np.ndarray, np.ndarray]:
    """EKF update of R filters with their registered poses as measurements of the pose.

    A measurement's covariance is ``POINT_SIGMA^2 (J^T J)^-1`` (the least-squares covariance of the
    registration) plus :data:`MEASUREMENT_FLOOR`, so directions the map does not constrain are left to
    the prediction.
    """
    xy, theta = MEASUREMENT_FLOOR
    noise = POINT_SIGMA**2 * np.linalg.inv(registered.information + 1e-9 * np.eye(3)) + np.diag(
        [xy**2, xy**2, theta**2]
    )
    gain = cov @ np.linalg.inv(cov + noise)
    innovation = registered.pose - mean
    innovation[:, 2] = wrap(innovation[:, 2])
    mean = mean + np.einsum("rij,rj->ri", gain, innovation)
    mean[:, 2] = wrap(mean[:, 2])
    return mean, (np.eye(3) - gain) @ cov


@dataclass
class ScanToMapEKF(Tracker):
    """The registration application (see the module docstring; run settings: :class:`~mi_lidar.apps.scans.Tracker`).

    Attributes:
        seed: seed of the runs' noise (noisy start and odometry).
    """

    seed: int = 0
    sweep: ClassVar[str] = "iterations"  # the parameter swept at the best real setting (thesis fig. 3.20)
    effort: ClassVar[str] = "icp_iterations"  # the metric shown beside J along the sweep
    name: str = "registration"
    objective: str = f"EKF mean position error, capped at {CAP:g} m (m)"
    parameters: tuple[Parameter, ...] = (
        Parameter("max_distance", (0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.2), start=1.2, unit="m"),
        Parameter("iterations", (1.0, 2.0, 3.0, 5.0, 8.0, 12.0, 20.0), start=1.0),
        Parameter("min_inliers", (0.0, 0.2, 0.4, 0.6, 0.8), start=0.0),
    )

    @staticmethod
    def index(states: PlanarStates, t: int) -> MapIndex:
        """The map index of state ``t``'s map (built once per map)."""
        g = states.maps.map_of(t)
        return states.memo(("map_index", g), lambda: MapIndex.build(states.maps.points(t)))

    def filter(self, alpha: dict, states: PlanarStates, ranges: np.ndarray, runs: np.ndarray) -> dict:
        """Run the filter along every stretch for run indices ``runs`` (R,); per-run arrays of what it did."""
        data = run_ranges(ranges, runs)
        starts, motions = noisy_runs(states, runs, self.seed)
        start_cov = np.diag([START_NOISE[0] ** 2, START_NOISE[0] ** 2, START_NOISE[1] ** 2])
        errors = np.empty((len(runs), states.n))
        headings, iterations, rejected = np.empty_like(errors), np.empty_like(errors), np.empty_like(errors, bool)
        cuts = stretches(states, self.stretch, self.max_states)
        for first, stop in cuts:
            mean, cov = starts[:, first].copy(), np.tile(start_cov, (len(runs), 1, 1))
            for t in range(first, stop):
                if t > first:
                    mean, cov = _predict(mean, cov, motions[:, t - 1])
                points, valid = scan_batch(data[:, t], states.angles)
                registered = icp_runs(
                    points, valid, self.index(states, t), mean, alpha["max_distance"], int(alpha["iterations"])
                )
                accept = (valid.sum(axis=1) >= 3) & (registered.share >= alpha["min_inliers"])
                if accept.any():
                    taken = Registration(*(v[accept] for v in vars(registered).values()))
                    mean[accept], cov[accept] = _update(mean[accept], cov[accept], taken)
                errors[:, t] = np.hypot(mean[:, 0] - states.poses[t, 0], mean[:, 1] - states.poses[t, 1])
                headings[:, t] = np.abs(wrap(mean[:, 2] - states.poses[t, 2]))
                iterations[:, t], rejected[:, t] = registered.iterations, ~accept
        used = stretch_mask(cuts, states.n)
        errors, headings, iterations, rejected = (v[:, used] for v in (errors, headings, iterations, rejected))
        return {
            "objective": np.minimum(errors, CAP).mean(axis=1),
            "errors": errors,
            "headings": headings,
            "iterations": iterations,
            "rejected": rejected,
        }

    def evaluate(self, alpha: dict, states: PlanarStates, ranges: np.ndarray) -> dict:
        """Run the filter along the states on ``ranges`` ((S, T, N) or (T, N)) with setting ``alpha``."""
        done = self.filter_runs(alpha, states, ranges)
        return {
            **tracker_metrics(done),
            "icp_iterations": float(done["iterations"].mean()),
            "rejected": float(done["rejected"].mean()),
            "error_p90": float(np.quantile(done["errors"], 0.9)),
        }
