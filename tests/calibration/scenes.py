"""Small calibration scenes: a bumpy bowl of terrain around the sensor, plus permeable ellipsoids."""

import numpy as np

from mi_lidar.calibration import EllipsoidElements, MeshElements
from mi_lidar.patterns import get_pattern

SENSOR_HEIGHT = 1.5  # m above the bowl's floor


def bowl_height(x, y):
    """Terrain height (m): a bowl rising 5 cm/m^2 with bumps, so every beam meets it at a slant."""
    return 0.05 * (x * x + y * y) + 0.4 * np.sin(0.5 * x) * np.cos(0.4 * y)


def bowl(n: int = 25, half: float = 12.0, p_hit=1.0, label: int = 1) -> MeshElements:
    """An (n-1)^2 x 2 triangle heightfield over [-half, half]^2 (m)."""
    g = np.linspace(-half, half, n)
    x, y = np.meshgrid(g, g, indexing="ij")
    vertices = np.c_[x.ravel(), y.ravel(), bowl_height(x, y).ravel()]
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
    faces = np.r_[np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    return MeshElements(vertices=vertices, faces=faces, p_hit=np.broadcast_to(p_hit, len(faces)).copy(),
                        label=np.full(len(faces), label))


def shrubs(p_hit, radius: float = 5.0) -> EllipsoidElements:
    """Len(p_hit) ellipsoids on a ring of ``radius`` m around the sensor, at sensor height."""
    n = len(p_hit)
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    centers = np.c_[radius * np.cos(angle), radius * np.sin(angle), np.full(n, SENSOR_HEIGHT + 0.2)]
    return EllipsoidElements(centers=centers, scales=np.tile([0.5, 0.6, 0.8], (n, 1)),
                             quaternions=np.tile([0, 0, 0, 1.0], (n, 1)), p_hit=np.asarray(p_hit, float),
                             label=np.full(n, 5), extent=3.0)


def sensor_pose(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """Upright sensor pose (4, 4) above the bowl at (x, y), turned by ``yaw`` rad."""
    pose = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    pose[:3, 3] = [x, y, bowl_height(x, y) + SENSOR_HEIGHT]
    return pose


def pattern(firings: int = 250):
    """A VLP-16 (16 beams) with ``firings`` firings per sweep."""
    return get_pattern("vlp16", n_firings=firings)
