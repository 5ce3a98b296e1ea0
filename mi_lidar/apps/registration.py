"""Scan-to-map registration in an EKF along the trajectory (thesis 3.5.2).

At each state the filter predicts the pose by the (noisy) odometry motion from the previous state
(:func:`~mi_lidar.apps.scans.noisy_run`), registers the scan to the state's map by point-to-line ICP
(:func:`icp`) from the prediction, and fuses the registered pose as a measurement of the pose (EKF
update, :func:`_update`). A registration whose inlier share is below the gate is rejected (prediction
only). With ``chained`` the prediction starts from the previous estimate (one filter along the whole
trajectory); without, from the previous true pose with the start covariance, so every state is one
registration instance: on logs whose states are seconds and metres apart (the protocol's test scans of
the Intel log: median 2.4 m and 68 deg between states) one lost registration otherwise loses the rest
of the run whatever the sensor model, and ``J`` measures luck more than registration.

========================  ============================================================  ======
alpha                     meaning                                                       unit
========================  ============================================================  ======
``max_distance``          a scan point farther than this from the map is an outlier      m
``iterations``            ICP refining iterations (it may converge in fewer)             -
``min_inliers``           reject a registration with a smaller share of inliers         -
========================  ============================================================  ======

``J``: the mean position error of the filter (m) over states and runs, against the SLAM-corrected
poses, each state's error capped at :data:`~mi_lidar.apps.scans.CAP` m (a lost filter counts as lost).
Also reported: the mean heading error (deg), the mean ICP iterations run (the thesis's convergence
time), the share of rejected registrations and the divergence rate (error > 1 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mi_lidar.apps.risk import Parameter
from mi_lidar.apps.scans import (
    CAP,
    START_NOISE,
    PlanarStates,
    compose,
    motion_sigma,
    noisy_run,
    scan_points,
    to_world,
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
    """Result of :func:`icp`.

    Attributes:
        pose: (3,) the registered pose.
        share: share of the scan's points within ``max_distance`` of the map at that pose.
        iterations: iterations run.
        information: (3, 3) ``sum J^T J`` of the point-to-line residuals at the pose (1/m^2 units per
            pose coordinate): small along directions the map does not constrain (a corridor's axis).
    """

    pose: np.ndarray
    share: float
    iterations: int
    information: np.ndarray


def _pairs(points: np.ndarray, index: MapIndex, pose: np.ndarray, max_distance: float):
    """Residuals (k,) and Jacobians (k, 3) of the point-to-line pairs within ``max_distance``, and the inlier share."""
    world = to_world(pose, points)
    distance, nearest = index.tree.query(world, distance_upper_bound=max_distance)
    inlier = np.isfinite(distance)
    p, n = world[inlier], index.normals[nearest[inlier]]
    residual = np.sum(n * (p - index.points[nearest[inlier]]), axis=1)
    arm = p - pose[:2]
    jacobian = np.stack([n[:, 0], n[:, 1], n[:, 1] * arm[:, 0] - n[:, 0] * arm[:, 1]], axis=1)
    return residual, jacobian, float(inlier.mean()) if len(points) else 0.0


def icp(
    points: np.ndarray, index: MapIndex, pose: np.ndarray, max_distance: float, iterations: int, tolerance=1e-4
) -> Registration:
    """Point-to-line ICP of laser-frame ``points`` (n, 2) to a map, from ``pose`` (3,).

    Each iteration pairs every point with its nearest map point within ``max_distance`` and takes one
    Gauss-Newton step on the sum of squared point-to-line distances; it stops after ``iterations``, when
    fewer than 3 pairs remain, or when a step moves less than ``tolerance`` (m, and rad).
    """
    pose = np.array(pose, np.float64)
    run = 0
    while run < iterations:
        run += 1
        residual, jacobian, _ = _pairs(points, index, pose, max_distance)
        if residual.size < 3:
            break
        step = np.linalg.solve(jacobian.T @ jacobian + 1e-6 * np.eye(3), -jacobian.T @ residual)
        pose = pose + step
        pose[2] = wrap(pose[2])
        if np.hypot(step[0], step[1]) < tolerance and abs(step[2]) < tolerance:
            break
    _, jacobian, share = _pairs(points, index, pose, max_distance)
    return Registration(pose=pose, share=share, iterations=run, information=jacobian.T @ jacobian)


def _predict(mean: np.ndarray, cov: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """EKF motion update by ``u`` (3,) in the robot frame, with the noise of :func:`motion_sigma`."""
    c, s = np.cos(mean[2]), np.sin(mean[2])
    f = np.array([[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]])
    w = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    q = np.diag(motion_sigma(u) ** 2)
    return compose(mean, u), f @ cov @ f.T + w @ q @ w.T


def _update(mean: np.ndarray, cov: np.ndarray, registered: Registration) -> tuple[np.ndarray, np.ndarray]:
    """EKF update with the registered pose as a measurement of the pose.

    Its covariance is ``POINT_SIGMA^2 (J^T J)^-1`` (the least-squares covariance of the registration)
    plus :data:`MEASUREMENT_FLOOR`, so directions the map does not constrain are left to the prediction.
    """
    xy, theta = MEASUREMENT_FLOOR
    noise = POINT_SIGMA**2 * np.linalg.inv(registered.information + 1e-9 * np.eye(3))
    gain = cov @ np.linalg.inv(cov + noise + np.diag([xy**2, xy**2, theta**2]))
    innovation = registered.pose - mean
    innovation[2] = wrap(innovation[2])
    mean = mean + gain @ innovation
    mean[2] = wrap(mean[2])
    return mean, (np.eye(3) - gain) @ cov


@dataclass
class ScanToMapEKF:
    """The registration application (see the module docstring).

    Attributes:
        runs: filter runs per evaluation (each with its own noisy start and odometry, the same on every dataset).
        seed: seed of the first run.
        chained: predict from the previous estimate (else from the previous true pose).
    """

    runs: int = 3
    seed: int = 0
    chained: bool = False
    name: str = "registration"
    objective: str = "EKF mean position error (m)"
    parameters: tuple[Parameter, ...] = (
        Parameter("max_distance", (0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.2), start=1.2, unit="m"),
        Parameter("iterations", (1.0, 2.0, 3.0, 5.0, 8.0, 12.0, 20.0), start=1.0),
        Parameter("min_inliers", (0.0, 0.2, 0.4, 0.6, 0.8), start=0.0),
    )

    @staticmethod
    def index(states: PlanarStates, t: int) -> MapIndex:
        """The map index of state ``t`` (built once per states)."""
        return states.memo(("map_index", t), lambda: MapIndex.build(states.maps.points(t)))

    def evaluate(self, alpha: dict, states: PlanarStates, ranges: np.ndarray) -> dict:
        """Run the filter ``runs`` times on ``ranges`` (T, N) with setting ``alpha``."""
        errors, headings, iterations, rejected = [], [], [], []
        for run in range(self.runs):
            mean, motions = noisy_run(states, self.seed + run)
            start = np.diag([START_NOISE[0] ** 2, START_NOISE[0] ** 2, START_NOISE[1] ** 2])
            cov = start
            for t in range(states.n):
                if t > 0 and self.chained:
                    mean, cov = _predict(mean, cov, motions[t - 1])
                elif t > 0:
                    mean, cov = _predict(states.poses[t - 1], start, motions[t - 1])
                points = scan_points(ranges[t], states.angles)
                registered = icp(points, self.index(states, t), mean, alpha["max_distance"], int(alpha["iterations"]))
                iterations.append(registered.iterations)
                accept = len(points) >= 3 and registered.share >= alpha["min_inliers"]
                rejected.append(not accept)
                if accept:
                    mean, cov = _update(mean, cov, registered)
                truth = states.poses[t]
                errors.append(float(np.hypot(*(mean[:2] - truth[:2]))))
                headings.append(float(abs(wrap(mean[2] - truth[2]))))
        return {
            "J": float(np.mean(np.minimum(errors, CAP))),
            "divergence": float(np.mean(np.asarray(errors) > 1.0)),
            "heading_error_deg": float(np.degrees(np.mean(headings))),
            "icp_iterations": float(np.mean(iterations)),
            "rejected": float(np.mean(rejected)),
            "error_p90": float(np.quantile(errors, 0.9)),
        }
