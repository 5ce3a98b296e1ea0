"""3D scan matching: register a scan to a map from perturbed initial poses (thesis ch. 4.4.2).

The application a robotics engineer tunes on simulated scans: scan-to-map registration by
`small_gicp <https://github.com/koide3/small_gicp>`_ (voxel-grid downsampling, then ICP,
point-to-plane ICP or GICP). Each evaluation registers the same scan from ``K`` initial poses, the
true pose perturbed by seeded offsets (:func:`perturbations`), and compares the registered pose with
the truth.

======================  =====================================================================  ====
alpha                   meaning                                                                unit
======================  =====================================================================  ====
``max_distance``        largest scan-to-map distance of a correspondence                       m
``voxel``               voxel size of the downsampling of scan and map                         m
``method``              0 point-to-point ICP, 1 point-to-plane ICP, 2 GICP                     -
``iterations``          largest number of Gauss-Newton iterations                              -
======================  =====================================================================  ====

``J``: the mean pose error over the ``K`` starts: translation error (m) plus
:data:`ROTATION_LEVER` times the rotation error (rad), i.e. how far a point 10 m away from the
sensor lands from where it should. Also reported: the mean translation (m) and rotation (deg)
errors, the share of starts that failed (translation error > 0.5 m or rotation error > 2 deg), and
``J`` of every start (for standard errors over the perturbations).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mi_lidar.apps.risk import Parameter
from mi_lidar.core.errors import ParameterError

ROTATION_LEVER = 10.0  # m: a rotation error counts as the displacement of a point this far away
FAILED = (0.5, 2.0)  # a start failed beyond this translation (m) or rotation (deg) error
METHODS = ("ICP", "PLANE_ICP", "GICP")


@dataclass
class FrameStates:
    """The states of one frame every source shares: the map, the scan's rays and the starts.

    Attributes:
        map_points: (M, 3) points of the map, world frame (m).
        origins: (N, 3) origins of the scan's rays, world frame (m).
        directions: (N, 3) unit directions of the scan's rays, world frame.
        starts: (K, 4, 4) initial guesses: the error of the initial pose, as a rigid transform applied
            to the scan's points (the identity is the truth).
        maps: the map preprocessed per voxel size (m), filled on demand (:meth:`map_cloud`).
    """

    map_points: np.ndarray
    origins: np.ndarray
    directions: np.ndarray
    starts: np.ndarray
    maps: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n(self) -> int:
        """Rays of the scan."""
        return len(self.origins)

    def map_cloud(self, voxel: float):
        """The map preprocessed at ``voxel`` (m) (:func:`preprocess`), computed once: every source registers to it."""
        if voxel not in self.maps:
            self.maps[voxel] = preprocess(self.map_points, voxel)
        return self.maps[voxel]


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (rad) about the unit ``axis`` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def perturbations(k: int, seed: int, translation: float = 1.0, yaw_deg: float = 5.0, tilt_deg: float = 1.0):
    """``k`` seeded initial-pose errors: a horizontal offset of ``translation`` m in a random direction
    plus N(0, (translation / 10)^2) vertically, a yaw of +-``yaw_deg`` (uniform) and a roll and pitch of
    +-``tilt_deg`` (uniform).

    Returns:
        (k, 4, 4) rigid transforms.
    """
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (k, 1, 1))
    for i in range(k):
        heading = rng.uniform(0, 2 * np.pi)
        yaw, roll, pitch = np.radians(rng.uniform(-1, 1, 3) * [yaw_deg, tilt_deg, tilt_deg])
        out[i, :3, :3] = rotation([0, 0, 1], yaw) @ rotation([1, 0, 0], roll) @ rotation([0, 1, 0], pitch)
        out[i, :3, 3] = [translation * np.cos(heading), translation * np.sin(heading), rng.normal(0, translation / 10)]
    return out


def pose_error(transform: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (rad) of a (4, 4) rigid transform (its distance from the identity)."""
    cos = np.clip((np.trace(transform[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.linalg.norm(transform[:3, 3])), float(np.arccos(cos))


def scan_cloud(states: FrameStates, ranges: np.ndarray) -> np.ndarray:
    """(P, 3) points of the rays that returned (finite ``ranges``, m), world frame."""
    r = np.asarray(ranges, float).ravel()
    keep = np.isfinite(r) & (r > 0)
    return states.origins[keep] + r[keep, None] * states.directions[keep]


NEIGHBORS = 10  # points of each normal / covariance estimate (small_gicp's default)


def preprocess(points: np.ndarray, voxel: float):
    """Downsample ``points`` on a ``voxel`` grid (m) and estimate normals and covariances: small_gicp's
    ``(PointCloud, KdTree)``, computed once per cloud and voxel size and shared by every start."""
    import small_gicp

    return small_gicp.preprocess_points(
        np.asarray(points, np.float64), downsampling_resolution=float(voxel), num_neighbors=NEIGHBORS
    )


def register(target, source, start: np.ndarray, alpha: dict) -> np.ndarray:
    """Register the preprocessed ``source`` to the preprocessed ``target`` (:func:`preprocess`) with small_gicp,
    starting from the transform ``start``.

    Both clouds are in the world frame at the true pose, so the truth is the identity and ``start`` is
    the initial-pose error.

    Returns:
        (4, 4) the estimated ``T_target_source``: the pose error that remains (identity when the
        registration recovered the truth).
    """
    import small_gicp

    (target_cloud, target_tree), (source_cloud, _) = target, source
    result = small_gicp.align(
        target_cloud,
        source_cloud,
        target_tree,
        init_T_target_source=np.asarray(start, np.float64),
        registration_type=METHODS[int(round(alpha["method"]))],
        max_correspondence_distance=float(alpha["max_distance"]),
        max_iterations=int(alpha["iterations"]),
        num_threads=1,
    )
    return np.asarray(result.T_target_source)


@dataclass(frozen=True)
class ScanMatching3D:
    """Scan-to-map registration from perturbed starts (see the module docstring)."""

    name: str = "scan_matching_3d"
    objective: str = f"mean pose error over the starts: translation (m) + {ROTATION_LEVER:g} m x rotation (rad)"
    parameters: tuple[Parameter, ...] = (
        Parameter("max_distance", (0.25, 0.5, 1.0, 2.0, 4.0), start=1.0, unit="m"),
        Parameter("voxel", (0.1, 0.2, 0.4, 0.8), start=0.2, unit="m"),
        Parameter("method", (0.0, 1.0, 2.0), start=2.0),
        Parameter("iterations", (5.0, 10.0, 20.0, 40.0), start=20.0),
    )

    def evaluate(self, alpha: dict, states: FrameStates, ranges: np.ndarray) -> dict:
        """Register the scan of ``ranges`` ((1, N) or (N,) m, NaN: no return) from every start.

        Raises:
            ParameterError: the scan has fewer than 10 returns.
        """
        source = scan_cloud(states, ranges)
        if len(source) < 10:
            raise ParameterError(f"{self.name}: the scan has {len(source)} returns; registration needs at least 10")
        target, scan = states.map_cloud(alpha["voxel"]), preprocess(source, alpha["voxel"])
        translation, angle = np.array([pose_error(register(target, scan, s, alpha)) for s in states.starts]).T
        per_start = translation + ROTATION_LEVER * angle
        failed = (translation > FAILED[0]) | (np.degrees(angle) > FAILED[1])
        return {
            "J": float(per_start.mean()),
            "J_starts": per_start.tolist(),
            "translation": float(translation.mean()),
            "rotation_deg": float(np.degrees(angle).mean()),
            "failed": float(failed.mean()),
            "points": int(len(source)),
        }
