"""A synthetic off-road "real world" that is richer than the hybrid model, and its true sensor.

The world is one triangle mesh with per-face class, instance and reflectance:

* procedural uneven terrain (sum of random sinusoids and bumps plus 3 cm roughness, 0.5 m grid);
* trees and shrubs of the thesis classes (:mod:`.classes`) made of a trunk or stems, branches
  (six-sided prisms) and many small randomly oriented leaf triangles filling an ellipsoidal
  crown, denser towards its surface;
* shrub patches (many shrubs of one class sharing a patch instance id >= ``PATCH_BASE``);
* grass patches (thin blades, 15-45 cm) and half-buried rocks;
* a vehicle path (a sine curve along +x) kept free of objects.

The **true sensor** (:class:`SensorSpec`) is a 32-beam spinning Lidar with beam divergence. Each
beam is traced as ``1 + n_ring`` sub-rays (centre weight 0.4, ring of ``n_ring`` sub-rays at half
the divergence angle sharing 0.6). Mixed pixels: the sub-ray hits within ``echo_window`` of the
nearest one form the first echo, whose range is the *energy-weighted average* of those sub-ray
ranges (weights = beam weight x reflectance x |cos incidence|); so a beam half on a leaf and half
on the trunk 40 cm behind returns a point in between. The echo is detected with probability
``1 - exp(-E / energy_scale)`` where ``E`` is that energy times ``min(1, (r_ref / r)^2)``; if it is
not detected, the remaining sub-rays form a second echo tried the same way. Detected ranges get
Gaussian noise ``range_noise`` (m); the label and instance are those of the sub-ray contributing
most energy. Rays are cast directly with Mitsuba (``scene.ray_intersect``) on a plain mesh scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.log import Log
from mi_lidar.hybrid.classes import CLASS_ID, PATCH_BASE

# (height range m, crown width / height, leaf density per m^3, leaf size m, is_tree)
CLASS_SHAPES = {
    "low_shrub": ((0.6, 1.2), 1.4, 60.0, 0.10, False),
    "small_shrub": ((1.2, 2.2), 1.2, 45.0, 0.12, False),
    "medium_shrub": ((2.2, 3.4), 1.0, 30.0, 0.14, False),
    "large_shrub": ((3.4, 4.8), 0.9, 22.0, 0.16, False),
    "small_tree": ((4.5, 7.0), 0.55, 18.0, 0.18, True),
    "medium_tree": ((7.0, 10.0), 0.5, 12.0, 0.20, True),
    "large_tree": ((10.0, 13.5), 0.45, 8.0, 0.24, True),
}
ROCK_SIZE = (0.3, 0.9)  # m, range of a rock's largest half-axis
REFLECTANCE = {"ground": 0.30, "grass": 0.35, "rock": 0.40, "leaf": 0.45, "bark": 0.25}


@dataclass
class WorldSpec:
    """Layout of a synthetic world.

    Attributes:
        length: extent along x, m (the path runs from x = 5 to x = length - 5).
        width: extent along y, m (centred on y = 0).
        object_density: objects per 100 m^2 (trees, shrubs, rocks), before rejection.
        n_patches: shrub patches.
        n_grass: grass patches.
        relief: terrain amplitude, m.
        corridor: half width of the object-free vehicle path, m.
    """

    length: float = 100.0
    width: float = 50.0
    object_density: float = 1.2
    n_patches: int = 2
    n_grass: int = 4
    relief: float = 1.2
    corridor: float = 3.0


@dataclass
class WorldObject:
    """Ground truth of one object: class, instance, pose (centre, yaw rad) and box extents (m)."""

    instance: int
    label: int
    center: np.ndarray
    yaw: float
    extents: np.ndarray
    patch: bool = False


@dataclass
class World:
    """The world mesh with per-face ``label``, ``instance``, ``reflectance`` and ``normal`` arrays.

    Attributes:
        vertices: (V, 3) float32, m.
        faces: (F, 3) int32.
        label, instance: (F,) int32 class id and instance id per face.
        reflectance: (F,) float32 in [0, 1].
        objects: ground-truth objects.
        spec: layout.
        seed: random seed that made the world.
        terrain: parameters of the height function (see :meth:`height`).
    """

    vertices: np.ndarray
    faces: np.ndarray
    label: np.ndarray
    instance: np.ndarray
    reflectance: np.ndarray
    objects: list[WorldObject]
    spec: WorldSpec
    seed: int
    terrain: dict
    _scene: object = field(default=None, repr=False)

    def height(self, x, y) -> np.ndarray:
        """Terrain height (m) at world coordinates ``x``, ``y`` (broadcastable arrays, m)."""
        return terrain_height(self.terrain, np.asarray(x, float), np.asarray(y, float))

    def path_y(self, x) -> np.ndarray:
        """y (m) of the vehicle path at ``x`` (m)."""
        return path_y(self.terrain, np.asarray(x, float))

    @property
    def normals(self) -> np.ndarray:
        """(F, 3) unit face normals."""
        v = self.vertices[self.faces]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def mitsuba_scene(self):
        """A Mitsuba scene holding the world mesh (built once)."""
        if self._scene is None:
            from mi_lidar.hybrid.trace import mesh_scene

            self._scene = mesh_scene(self.vertices, self.faces)
        return self._scene


# --------------------------------------------------------------------------- terrain and path
def terrain_height(terrain: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height (m) of the terrain described by ``terrain`` at ``x``, ``y`` (m)."""
    z = np.zeros(np.broadcast(x, y).shape)
    for a, kx, ky, ph in terrain["waves"]:
        z += a * np.sin(kx * x + ky * y + ph)
    for a, cx, cy, s in terrain["bumps"]:
        z += a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    return z


def path_y(terrain: dict, x: np.ndarray) -> np.ndarray:
    """y (m) of the vehicle path at ``x`` (m): a sine of amplitude ``terrain['path'][0]``."""
    amp, period, phase = terrain["path"]
    return amp * np.sin(2 * np.pi * x / period + phase)


def _make_terrain(spec: WorldSpec, rng: np.random.Generator) -> dict:
    waves = []
    for _ in range(5):
        wavelength = rng.uniform(15, 60)
        theta = rng.uniform(0, np.pi)
        k = 2 * np.pi / wavelength
        waves.append(
            (spec.relief * rng.uniform(0.2, 0.5), k * np.cos(theta), k * np.sin(theta), rng.uniform(0, 2 * np.pi))
        )
    bumps = [
        (
            spec.relief * rng.uniform(-1, 1),
            rng.uniform(0, spec.length),
            rng.uniform(-spec.width / 2, spec.width / 2),
            rng.uniform(3, 8),
        )
        for _ in range(int(spec.length * spec.width / 400) + 1)
    ]
    path = (rng.uniform(2, 0.12 * spec.width), rng.uniform(60, 140), rng.uniform(0, 2 * np.pi))
    return {"waves": waves, "bumps": bumps, "path": path}


def _terrain_mesh(spec: WorldSpec, terrain: dict, rng, step: float = 0.5):
    nx, ny = int(spec.length / step) + 1, int(spec.width / step) + 1
    xs, ys = np.linspace(0, spec.length, nx), np.linspace(-spec.width / 2, spec.width / 2, ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    gz = terrain_height(terrain, gx, gy) + rng.normal(0, 0.03, gx.shape)
    verts = np.stack([gx, gy, gz], -1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


# --------------------------------------------------------------------------- geometry pieces
def _random_frames(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = rng.normal(size=(n, 3))
    v -= np.sum(v * u, axis=1, keepdims=True) * u
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return u, v


def leaf_triangles(centers: np.ndarray, size: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Randomly oriented equilateral triangles of circumradius ``size`` (m) at ``centers`` (n, 3)."""
    n = len(centers)
    u, v = _random_frames(n, rng)
    s = size * rng.uniform(0.7, 1.3, (n, 1))
    p0 = centers + s * u
    p1 = centers + s * (-0.5 * u + 0.866 * v)
    p2 = centers + s * (-0.5 * u - 0.866 * v)
    verts = np.stack([p0, p1, p2], 1).reshape(-1, 3)
    return verts, np.arange(3 * n).reshape(n, 3)


def prism(p0: np.ndarray, p1: np.ndarray, r0: float, r1: float, sides: int = 6):
    """Side triangles of a tapered ``sides``-gon prism from ``p0`` to ``p1`` (m), radii r0, r1 (m)."""
    axis = p1 - p0
    axis = axis / max(np.linalg.norm(axis), 1e-9)
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    ang = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2
    verts = np.concatenate([p0 + r0 * ring, p1 + r1 * ring])
    i = np.arange(sides)
    j = (i + 1) % sides
    faces = np.concatenate([np.stack([i, j, sides + j], 1), np.stack([i, sides + j, sides + i], 1)])
    return verts, faces


def _crown_points(n: int, center, radii, rng) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0, 1, (n, 1)) ** (1 / 5)  # concentrated towards the crown surface
    return center + d * r * radii


class _MeshBuilder:
    """Accumulates triangle soups with per-face label, instance and reflectance."""

    def __init__(self):
        self.parts = []
        self.count = 0

    def add(self, verts, faces, label, instance, reflectance):
        self.parts.append((np.asarray(verts, np.float32), np.asarray(faces) + self.count, label, instance, reflectance))
        self.count += len(verts)

    def build(self):
        verts = np.concatenate([p[0] for p in self.parts])
        faces = np.concatenate([p[1] for p in self.parts]).astype(np.int32)
        per_face = lambda k, dt: np.concatenate([np.full(len(p[1]), p[k], dt) for p in self.parts])
        return verts, faces, per_face(2, np.int32), per_face(3, np.int32), per_face(4, np.float32)


def _vegetation(
    builder: _MeshBuilder, cls: str, base: np.ndarray, height: float, yaw: float, instance: int, rng
) -> np.ndarray:
    """Add one tree or shrub standing at ``base`` (m); return its box extents (m)."""
    _, width_ratio, density, leaf, is_tree = CLASS_SHAPES[cls]
    label = CLASS_ID[cls]
    width = height * width_ratio * rng.uniform(0.8, 1.2)
    aspect = rng.uniform(0.7, 1.0)
    radii = np.array([width / 2, width / 2 * aspect, 0.0])
    if is_tree:
        crown_base = height * rng.uniform(0.3, 0.5)
        radii[2] = (height - crown_base) / 2
        trunk_r = 0.03 * height
        v, f = prism(base - [0, 0, 0.2], base + [0, 0, crown_base + radii[2]], trunk_r, trunk_r * 0.4)
        builder.add(v, f, label, instance, REFLECTANCE["bark"])
    else:
        radii[2] = height / 2
        crown_base = 0.0
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    center = base + np.array([0, 0, crown_base + radii[2]])
    n_branch = int(6 + 2 * height)
    for _ in range(n_branch):
        tip = center + rot @ (radii * _crown_points(1, 0, 0.8, rng)[0])
        start = (
            center - [0, 0, radii[2] * rng.uniform(0.2, 0.9)] if is_tree else base + rng.normal(0, 0.1, 3) * [1, 1, 0]
        )
        v, f = prism(start, tip, 0.012 * height if is_tree else 0.02, 0.01)
        builder.add(v, f, label, instance, REFLECTANCE["bark"])
    volume = 4 / 3 * np.pi * radii.prod()
    n_leaves = int(density * volume)
    pts = _crown_points(n_leaves, np.zeros(3), radii, rng) @ rot.T + center
    pts[:, 2] = np.maximum(pts[:, 2], base[2] + 0.05)
    v, f = leaf_triangles(pts, leaf, rng)
    builder.add(v, f, label, instance, REFLECTANCE["leaf"])
    ext = np.array([width, width * aspect, height])
    return ext


def _rock(builder: _MeshBuilder, base: np.ndarray, size: float, yaw: float, instance: int, rng) -> np.ndarray:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    radii = size * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.4, 0.7)])
    v = sphere.vertices * radii * rng.uniform(0.85, 1.15, (len(sphere.vertices), 1))
    c, s = np.cos(yaw), np.sin(yaw)
    v = v @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + base + [0, 0, 0.2 * radii[2]]
    builder.add(v, sphere.faces, CLASS_ID["rock"], instance, REFLECTANCE["rock"])
    return 2 * radii * [1, 1, 0.6]


def object_mesh(cls: str, size: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One object of the world's generator standing on the origin, unrotated (yaw 0).

    Args:
        cls: an object class name (a key of ``CLASS_SHAPES`` or ``"rock"``).
        size: tree or shrub height, or a rock's largest half-axis, m.
        rng: random generator drawing the object's shape, branches and leaves.

    Returns:
        (V, 3) float32 vertices, m (the base at the origin, z up, the wider side along x) and
        (F, 3) int32 faces.
    """
    builder = _MeshBuilder()
    if cls == "rock":
        _rock(builder, np.zeros(3), size, 0.0, 1, rng)
    else:
        _vegetation(builder, cls, np.zeros(3), size, 0.0, 1, rng)
    vertices, faces, *_ = builder.build()
    return vertices, faces


def _grass(builder: _MeshBuilder, world_h, center, radius: float, rng, density: float = 30.0):
    n = int(density * np.pi * radius**2)
    r = radius * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    x, y = center[0] + r * np.cos(a), center[1] + r * np.sin(a)
    z = world_h(x, y)
    base = np.stack([x, y, z], 1)
    h = rng.uniform(0.15, 0.45, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    side = 0.02 * np.stack([np.cos(phi), np.sin(phi), 0 * phi], 1)
    lean = 0.3 * h[:, None] * np.stack([-np.sin(phi), np.cos(phi), 0 * phi], 1) * rng.uniform(-1, 1, (n, 1))
    tip = base + lean + h[:, None] * [0, 0, 1]
    verts = np.stack([base - side, base + side, tip], 1).reshape(-1, 3)
    builder.add(verts, np.arange(3 * n).reshape(n, 3), CLASS_ID["grass"], 0, REFLECTANCE["grass"])


def make_world(seed: int, spec: WorldSpec | None = None) -> World:
    """Build a random world; different seeds give different terrain, path and layouts.

    Args:
        seed: random seed.
        spec: layout (defaults to :class:`WorldSpec`).

    Returns:
        The :class:`World`.
    """
    spec = spec or WorldSpec()
    rng = np.random.default_rng(seed)
    terrain = _make_terrain(spec, rng)
    h = lambda x, y: terrain_height(terrain, x, y)
    builder = _MeshBuilder()
    builder.add(*_terrain_mesh(spec, terrain, rng), CLASS_ID["ground"], 0, REFLECTANCE["ground"])
    objects: list[WorldObject] = []
    occupied: list[tuple[float, float, float]] = []

    def free(x, y, r):
        if abs(y - path_y(terrain, x)) < spec.corridor + r or not (r < x < spec.length - r):
            return False
        return all((x - ox) ** 2 + (y - oy) ** 2 > (r + orad) ** 2 for ox, oy, orad in occupied)

    def sample_position(r):
        for _ in range(50):
            x, y = rng.uniform(0, spec.length), rng.uniform(-spec.width / 2 + r, spec.width / 2 - r)
            if free(x, y, r):
                return x, y
        return None

    classes = list(CLASS_SHAPES) + ["rock"]
    weights = np.array([0.5, 1.2, 1.0, 0.7, 1.0, 0.8, 0.5, 0.8])
    n_objects = int(spec.object_density * spec.length * spec.width / 100)
    # shrub patches first: many shrubs of one class in an ellipse, one patch instance
    for p in range(spec.n_patches):
        cls = ["low_shrub", "small_shrub", "medium_shrub"][rng.integers(0, 3)]
        hr = CLASS_SHAPES[cls][0]
        rad = rng.uniform(4, 7)
        pos = sample_position(rad)
        if pos is None:
            continue
        occupied.append((pos[0], pos[1], rad))
        instance = PATCH_BASE + p
        ext_lo, ext_hi = np.full(3, np.inf), np.full(3, -np.inf)
        for _ in range(int(rad * rad * 0.9)):
            rr, aa = rad * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
            x, y = pos[0] + rr * np.cos(aa), pos[1] + rr * np.sin(aa)
            height = rng.uniform(*hr)
            base = np.array([x, y, h(x, y)])
            ext = _vegetation(builder, cls, base, height, rng.uniform(0, 2 * np.pi), instance, rng)
            ext_lo = np.minimum(ext_lo, base - ext / 2 * [1, 1, 0])
            ext_hi = np.maximum(ext_hi, base + ext / 2 * [1, 1, 2])
        objects.append(WorldObject(instance, CLASS_ID[cls], (ext_lo + ext_hi) / 2, 0.0, ext_hi - ext_lo, patch=True))
    for i in range(n_objects):
        cls = classes[rng.choice(len(classes), p=weights / weights.sum())]
        if cls == "rock":
            size = rng.uniform(*ROCK_SIZE)
            rad = size
        else:
            height = rng.uniform(*CLASS_SHAPES[cls][0])
            rad = height * CLASS_SHAPES[cls][1] / 2
        pos = sample_position(rad + 0.5)
        if pos is None:
            continue
        occupied.append((pos[0], pos[1], rad + 0.5))
        base = np.array([pos[0], pos[1], h(*pos)])
        yaw = rng.uniform(0, np.pi)
        instance = i + 1
        if cls == "rock":
            ext = _rock(builder, base, size, yaw, instance, rng)
        else:
            ext = _vegetation(builder, cls, base, height, yaw, instance, rng)
        objects.append(WorldObject(instance, CLASS_ID[cls], base + [0, 0, ext[2] / 2], yaw, ext))
    for _ in range(spec.n_grass):
        cx, cy = rng.uniform(0, spec.length), rng.uniform(-spec.width / 2, spec.width / 2)
        _grass(builder, h, (cx, cy), rng.uniform(2, 5), rng)
    verts, faces, label, instance, refl = builder.build()
    return World(verts, faces, label, instance, refl, objects, spec, seed, terrain)


# --------------------------------------------------------------------------- the true sensor
@dataclass
class SensorSpec:
    """The true sensor: an HDL-32E-like spinning Lidar with beam divergence.

    Attributes:
        n_beams: rows H; elevations evenly spaced in [elev_min, elev_max] (deg).
        n_firings: columns W per 360 deg sweep.
        divergence: full beam divergence, rad.
        n_ring: sub-rays on the ring at half the divergence angle (plus one central sub-ray).
        range_noise: standard deviation of the Gaussian range noise, m.
        min_range, max_range: reported range limits, m.
        echo_window: sub-ray hits within this range of the nearest one form one echo, m.
        energy_scale: echo energy giving detection probability 1 - 1/e.
        r_ref: range below which the received energy saturates, m.
        sweep_time: duration of a sweep, s.
        mount_height: sensor height above the terrain, m.
    """

    n_beams: int = 32
    elev_min: float = -30.67
    elev_max: float = 10.67
    n_firings: int = 512
    divergence: float = 0.004
    n_ring: int = 6
    range_noise: float = 0.02
    min_range: float = 1.0
    max_range: float = 80.0
    echo_window: float = 1.0
    energy_scale: float = 0.05
    r_ref: float = 20.0
    sweep_time: float = 0.1
    mount_height: float = 1.8

    def directions(self) -> np.ndarray:
        """(H, W, 3) float32 central unit ray directions in the sensor frame (x forward, z up)."""
        elev = np.deg2rad(np.linspace(self.elev_max, self.elev_min, self.n_beams))
        az = 2 * np.pi * np.arange(self.n_firings) / self.n_firings
        e, a = np.meshgrid(elev, az, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).astype(np.float32)

    def sub_rays(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-ray directions (..., 1 + n_ring, 3) around unit directions ``d`` (..., 3) and weights."""
        helper = np.where(np.abs(d[..., 2:3]) < 0.9, [0, 0, 1.0], [1.0, 0, 0])
        e1 = np.cross(d, helper)
        e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = np.cross(d, e1)
        ang = 2 * np.pi * np.arange(self.n_ring) / self.n_ring
        ang = ang.reshape((-1,) + (1,) * d.ndim)
        ring = d[None] + np.tan(self.divergence / 4) * (np.cos(ang) * e1[None] + np.sin(ang) * e2[None])
        subs = np.concatenate([d[None], ring])
        subs /= np.linalg.norm(subs, axis=-1, keepdims=True)
        weights = np.array([0.4] + [0.6 / self.n_ring] * self.n_ring)
        return np.moveaxis(subs, 0, -2), weights


def path_poses(world: World, spacing: float = 1.5, sensor: SensorSpec | None = None, margin: float = 8.0) -> np.ndarray:
    """(S, 4, 4) sensor-to-world poses every ``spacing`` m (in x) along the world's vehicle path.

    The sensor sits ``mount_height`` above the terrain, yawed along the path tangent.

    Raises:
        ParameterError: ``spacing`` leaves no scan on the path.
    """
    sensor = sensor or SensorSpec()
    xs = np.arange(margin, world.spec.length - margin, spacing)
    if xs.size == 0 or not spacing > 0:
        raise ParameterError(
            f"spacing={spacing} m leaves no scan on the {world.spec.length:g} m world's path (x = {margin:g} to "
            f"{world.spec.length - margin:g} m); choose a spacing below {max(world.spec.length - 2 * margin, 0):g} m "
            "or a longer world"
        )
    ys = world.path_y(xs)
    dy = (world.path_y(xs + 0.1) - world.path_y(xs - 0.1)) / 0.2
    yaw = np.arctan2(dy, 1.0)
    poses = np.tile(np.eye(4), (len(xs), 1, 1))
    c, s = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :3, 3] = np.stack([xs, ys, world.height(xs, ys) + sensor.mount_height], 1)
    return poses


def _echo(r, energy, active, window):
    """Energy-weighted mean range, energy and mask of the first echo among ``active`` sub-rays."""
    rr = np.where(active, r, np.inf)
    r_min = rr.min(axis=1, keepdims=True)
    member = active & (rr <= r_min + window)
    e = np.where(member, energy, 0.0)
    total = e.sum(axis=1)
    mean = np.where(total > 0, (e * np.where(member, r, 0)).sum(axis=1) / np.maximum(total, 1e-12), np.nan)
    return mean, total, member


def render_log(
    world: World, poses: np.ndarray, sensor: SensorSpec | None = None, seed: int = 0, scans_per_batch: int = 8
) -> Log:
    """Ray-cast the true sensor in ``world`` at ``poses`` and return a labeled :class:`Log`.

    Args:
        world: the synthetic world.
        poses: (S, 4, 4) sensor-to-world transforms.
        sensor: the true sensor (defaults to :class:`SensorSpec`).
        seed: seed of detection and range noise.
        scans_per_batch: scans traced per Mitsuba call (memory vs. call overhead).

    Returns:
        A log with attributes ``label`` and ``instance`` (int32; 0 / -1 for misses).
    """
    from mi_lidar.hybrid.trace import intersect

    sensor = sensor or SensorSpec()
    rng = np.random.default_rng(seed)
    dirs = sensor.directions()
    subs, weights = sensor.sub_rays(dirs)  # (H, W, K, 3)
    h, w, k = subs.shape[:3]
    normals = world.normals
    s_count = len(poses)
    ranges = np.full((s_count, h, w), np.nan, np.float32)
    labels = np.zeros((s_count, h, w), np.int32)
    instances = np.full((s_count, h, w), -1, np.int32)
    scene = world.mitsuba_scene()
    for s0 in range(0, s_count, scans_per_batch):
        batch = poses[s0 : s0 + scans_per_batch]
        b = len(batch)
        d_world = np.einsum("bij,hwkj->bhwki", batch[:, :3, :3], subs).reshape(-1, 3)
        o_world = np.broadcast_to(batch[:, None, None, None, :3, 3], (b, h, w, k, 3)).reshape(-1, 3)
        t, prim = intersect(scene, o_world, d_world)
        t = t.reshape(-1, k)
        prim = prim.reshape(-1, k)
        valid = np.isfinite(t) & (t <= sensor.max_range)
        safe = np.where(valid, prim, 0)
        cos = np.abs(np.sum(normals[safe] * d_world.reshape(-1, k, 3), axis=-1))
        energy = weights * world.reflectance[safe] * cos * valid
        falloff = lambda r: np.minimum(1.0, (sensor.r_ref / np.maximum(r, 1e-3)) ** 2)
        r1, e1, m1 = _echo(t, energy, valid, sensor.echo_window)
        det1 = rng.uniform(size=len(r1)) < 1 - np.exp(-e1 * falloff(np.nan_to_num(r1, nan=1e9)) / sensor.energy_scale)
        r2, e2, m2 = _echo(t, energy, valid & ~m1, sensor.echo_window)
        det2 = rng.uniform(size=len(r2)) < 1 - np.exp(-e2 * falloff(np.nan_to_num(r2, nan=1e9)) / sensor.energy_scale)
        use2 = ~det1 & det2
        r = np.where(det1, r1, np.where(use2, r2, np.nan))
        member = np.where(use2[:, None], m2, m1)
        best = np.argmax(np.where(member, energy, -1), axis=1)
        face = safe[np.arange(len(best)), best]
        r = r + rng.normal(0, sensor.range_noise, len(r))
        ok = np.isfinite(r) & (r >= sensor.min_range) & (r <= sensor.max_range)
        ranges[s0 : s0 + b] = np.where(ok, r, np.nan).reshape(b, h, w)
        labels[s0 : s0 + b] = np.where(ok, world.label[face], 0).reshape(b, h, w)
        instances[s0 : s0 + b] = np.where(ok, world.instance[face], -1).reshape(b, h, w)
    hit = np.isfinite(ranges)
    col_time = np.arange(w) / w * sensor.sweep_time
    times = (np.arange(s_count)[:, None, None] * sensor.sweep_time + col_time[None, None, :]) * np.ones((1, h, 1))
    meta = {
        "name": "synthetic-true-sensor",
        "world_seed": world.seed,
        "min_range": sensor.min_range,
        "max_range": sensor.max_range,
        "divergence": sensor.divergence,
        "range_noise": sensor.range_noise,
    }
    return Log(
        poses=poses,
        directions=dirs[None],
        ranges=ranges,
        hit=hit,
        times=times,
        attributes={"label": labels, "instance": instances},
        sensor=meta,
    )
