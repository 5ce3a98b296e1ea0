"""Small calibration scenes: a bumpy bowl of terrain around the sensor, plus permeable ellipsoids."""

import numpy as np

import mi_lidar
from mi_lidar.core.effects import parse_effects
from mi_lidar.core.patterns import get_pattern
from mi_lidar.core.sensor_model import SensorModel
from mi_lidar.scene.dicts import EllipsoidElements, MeshElements, scene_dict

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
    return MeshElements(
        vertices=vertices,
        faces=faces,
        p_hit=np.broadcast_to(p_hit, len(faces)).copy(),
        label=np.full(len(faces), label),
    )


def shrubs(p_hit, radius: float = 5.0) -> EllipsoidElements:
    """Len(p_hit) ellipsoids on a ring of ``radius`` m around the sensor, at sensor height."""
    n = len(p_hit)
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    centers = np.c_[radius * np.cos(angle), radius * np.sin(angle), np.full(n, SENSOR_HEIGHT + 0.2)]
    return EllipsoidElements(
        centers=centers,
        scales=np.tile([0.5, 0.6, 0.8], (n, 1)),
        quaternions=np.tile([0, 0, 0, 1.0], (n, 1)),
        p_hit=np.asarray(p_hit, float),
        label=np.full(n, 5),
        extent=3.0,
    )


def sensor_pose(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """Upright sensor pose (4, 4) above the bowl at (x, y), turned by ``yaw`` rad."""
    pose = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    pose[:3, 3] = [x, y, bowl_height(x, y) + SENSOR_HEIGHT]
    return pose


def circle_poses(n: int) -> np.ndarray:
    """(n, 4, 4) sensor poses on a circle of 0.4 m around the bowl's centre, each turned by its angle on the circle."""
    return np.stack(
        [sensor_pose(0.4 * np.cos(a), 0.4 * np.sin(a), a) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]
    )


def pattern(firings: int = 250):
    """A VLP-16 (16 beams) with ``firings`` firings per sweep."""
    return get_pattern("vlp16", n_firings=firings)


WALL_X = 10.0  # m: the wall of floor_and_wall() is the plane x = WALL_X
WALL_HALF = 40.0  # m: it spans |y| <= WALL_HALF and 0 <= z <= WALL_HALF


def floor_and_wall() -> dict:
    """Opaque element sets: a 1 km floor at z = 0 and a wall at x = WALL_X, two triangles each."""
    floor = np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0]], float)
    wall = np.array(
        [
            [WALL_X, -WALL_HALF, 0],
            [WALL_X, WALL_HALF, 0],
            [WALL_X, WALL_HALF, WALL_HALF],
            [WALL_X, -WALL_HALF, WALL_HALF],
        ],
        float,
    )
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    return {
        name: MeshElements(vertices=v, faces=quad, p_hit=np.ones(2), label=np.ones(2))
        for name, v in (("floor", floor), ("wall", wall))
    }


SCAN_HEIGHT = 2.0  # m: floor_and_wall_scan()'s default sensor stands this high above the floor, at the origin


def floor_and_wall_scan(
    effects: str, seed: int, range_sigma: float = 0.03, firings: int = 300, pose: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One VLP-16 scan of ``firings`` firings above floor_and_wall() with the effects ``effects``.

    Args:
        effects: the effects of the sensor model, as ``--effect`` takes them ("" for none).
        seed: simulation seed.
        range_sigma: the elements' range noise (m).
        firings: firings of the sweep.
        pose: (4, 4) sensor pose (default: upright, :data:`SCAN_HEIGHT` m above the origin).

    Returns:
        (16, firings) ranges (m) and hit flags.
    """
    if pose is None:
        pose = np.eye(4)
        pose[2, 3] = SCAN_HEIGHT
    model = SensorModel(range_sigma=range_sigma, effects=parse_effects(effects))
    log = mi_lidar.simulate(
        mi_lidar.load_scene(scene_dict(floor_and_wall())), pattern(firings), poses=pose, seed=seed, model=model
    )
    return log.ranges[0], log.hit[0]


def analytic_ranges(origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Range (m) to the first of floor_and_wall()'s planes along (..., 3) rays (inf where none is hit)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(direction[..., 2] < 0, -origin[..., 2] / direction[..., 2], np.inf)
        t_wall = np.where(direction[..., 0] > 0, (WALL_X - origin[..., 0]) / direction[..., 0], np.inf)
    at_wall = origin + t_wall[..., None] * direction
    inside = (np.abs(at_wall[..., 1]) <= WALL_HALF) & (at_wall[..., 2] >= 0) & (at_wall[..., 2] <= WALL_HALF)
    return np.minimum(t_floor, np.where(inside, t_wall, np.inf))


def unit_directions(elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """(..., 3) unit vectors of elevation and azimuth angles (rad; x forward, z up)."""
    return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1)


def bushes(n: int = 24, seed: int = 0) -> EllipsoidElements:
    """``n`` rotated ellipsoids 3-6 m around the sensor near its height, scales 0.3-0.6 m, seeded."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    radius = rng.uniform(3.0, 6.0, n)
    yaw = rng.uniform(0, np.pi, n)
    centers = np.c_[radius * np.cos(angle), radius * np.sin(angle), SENSOR_HEIGHT + rng.uniform(-0.4, 0.4, n)]
    return EllipsoidElements(
        centers=centers,
        scales=rng.uniform(0.3, 0.6, (n, 3)),
        quaternions=np.c_[np.zeros((n, 2)), np.sin(yaw / 2), np.cos(yaw / 2)],
        p_hit=rng.uniform(0.3, 0.7, n),
        label=np.full(n, 5),
        extent=3.0,
    )
