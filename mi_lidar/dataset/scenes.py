"""Scenes of a dataset: loaded XML files, annotations filled from a primitive library, random annotations.

Every scene comes with its labelled 3D boxes (one per object, an instance id each), the instance id of
every shape, class names of its element labels, and a ground-height function for the trajectory.
Random annotations follow thesis ch. 4.3: objects of the library's classes placed along the path,
each one a library primitive of its class standing on the ground, drawn from
``default_rng([seed, scene, variant])`` so a variant is the same on every worker.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

from mi_lidar.core.elements import ElementTable
from mi_lidar.core.errors import SceneError, SpecError
from mi_lidar.core.frames import scene_origin
from mi_lidar.core.scene_shapes import registry_id
from mi_lidar.dataset.spec import DatasetSpec, SceneSpec
from mi_lidar.hybrid.blocks import read_mesh_ply
from mi_lidar.hybrid.classes import CLASS_ID, CLASS_NAMES
from mi_lidar.hybrid.compose import compose_scene, load_annotation
from mi_lidar.hybrid.element_sets import hybrid_element_sets
from mi_lidar.hybrid.model import GroundMesh
from mi_lidar.hybrid.primitives import PrimitiveLibrary, rotation_z
from mi_lidar.scene.dicts import EllipsoidElements, ellipsoids_dict, scene_dict
from mi_lidar.scene.loading import load_scene

LIGHTS = {  # the same sky and sun as the bundled XML scenes (the Lidar ignores emitters)
    "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.6, 0.7, 0.9]}},
    "sun": {
        "type": "directional",
        "direction": [-0.5, 0.3, -1.0],
        "irradiance": {"type": "rgb", "value": [3.0, 2.9, 2.7]},
    },
}
FOLIAGE = [0.12, 0.3, 0.08]  # diffuse albedo of vegetation ellipsoids in camera images
ROCK = [0.35, 0.33, 0.3]
FLAT_GROUND_MARGIN = 60.0  # m around the trajectory covered by the default flat ground


@dataclass(frozen=True)
class Box3D:
    """An object's oriented 3D box in the world frame.

    Attributes:
        class_name: the object's class. instance: its instance id (>= 1).
        center: (3,) geometric centre of the box, m. size: (3,) side lengths along the box's own x,
            y, z axes (length, width, height), m. yaw: rotation of the box's x axis about world z, rad.
    """

    class_name: str
    instance: int
    center: np.ndarray
    size: np.ndarray
    yaw: float

    def corners(self) -> np.ndarray:
        """(8, 3) world corners, m."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        return self.center + (signs * self.size / 2) @ rotation_z(self.yaw).T


@dataclass
class SceneInstance:
    """A loaded scene and what the dataset writer needs to label it.

    Attributes:
        scene: the Mitsuba scene. boxes: labelled objects. shape_instance: instance id per shape id
            (shapes absent are stuff, instance 0). label_names: class name per element label (label 0,
            also that of returns of no element, is ``unlabeled`` unless the spec names it).
        ground_height: ``f(x, y) -> z`` (m) on the ground mesh, None for XML scenes.
        shape_ids: the scene's element-table shape ids (the simulator's ``shape_id`` indexes them).
        instance_of_shape: instance id per Dr.Jit registry id of the scene's shapes (what ``si.shape``
            carries; 0 for stuff and for index 0, no shape).
    """

    scene: object
    boxes: list[Box3D]
    shape_instance: dict[str, int]
    label_names: dict[int, str]
    ground_height: Callable | None = None
    shape_ids: list[str] = field(default_factory=list)
    instance_of_shape: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))


def shape_bounds(scene) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """World bounding box (min (3,), max (3,)) of every shape with an id, m (a georeferenced scene's local
    origin added back)."""
    bounds, origin = {}, scene_origin(scene)
    for shape in scene.shapes():
        box = shape.bbox()
        bounds[shape.id()] = (
            np.array(box.min, dtype=np.float64) + origin,
            np.array(box.max, dtype=np.float64) + origin,
        )
    return bounds


def instance_by_registry(scene, shape_instance: dict[str, int]) -> np.ndarray:
    """Instance id per Dr.Jit registry id of the scene's shapes (``si.shape`` carries it); 0 for the rest."""
    registry = {registry_id(s): shape_instance.get(s.id(), 0) for s in scene.shapes()}
    table = np.zeros(max(registry, default=0) + 1, np.int64)
    table[list(registry)] = list(registry.values())
    return table


def xml_scene(spec: DatasetSpec, scene_spec: SceneSpec) -> SceneInstance:
    """An XML scene with the boxes of its listed objects (axis-aligned around their shapes)."""
    scene = load_scene(spec.resolve(scene_spec.xml), **scene_spec.parameters)
    bounds = shape_bounds(scene)
    boxes, shape_instance = [], {}
    for i, obj in enumerate(scene_spec.objects):
        unknown = [s for s in obj.shapes if s not in bounds]
        if unknown:
            raise SpecError(
                f"scene {scene_spec.name!r}: object {i} names shapes {unknown} that {scene_spec.xml} does not have; "
                f"its shape ids are {', '.join(sorted(bounds))}"
            )
        low = np.min([bounds[s][0] for s in obj.shapes], axis=0)
        high = np.max([bounds[s][1] for s in obj.shapes], axis=0)
        boxes.append(Box3D(obj.class_name, i + 1, (low + high) / 2, high - low, 0.0))
        shape_instance.update({s: i + 1 for s in obj.shapes})
    return SceneInstance(scene, boxes, shape_instance, {0: "unlabeled", **scene_spec.labels})


def height_function(ground: GroundMesh) -> Callable:
    """``f(x, y) -> z``: linear interpolation on the ground mesh's vertices, nearest outside it (m)."""
    xy, z = ground.vertices[:, :2], ground.vertices[:, 2]
    linear, nearest = LinearNDInterpolator(xy, z), NearestNDInterpolator(xy, z)

    def height(x, y):
        value = linear(x, y)
        return np.where(np.isnan(value), nearest(x, y), value)

    return height


def flat_ground(waypoints: np.ndarray, height: float = 0.0) -> GroundMesh:
    """Two opaque triangles covering the waypoints' extent plus :data:`FLAT_GROUND_MARGIN` (m)."""
    low, high = waypoints[:, :2].min(0) - FLAT_GROUND_MARGIN, waypoints[:, :2].max(0) + FLAT_GROUND_MARGIN
    corners = np.array([[low[0], low[1]], [high[0], low[1]], [high[0], high[1]], [low[0], high[1]]])
    return GroundMesh(
        np.c_[corners, np.full(4, height)],
        np.array([[0, 1, 2], [0, 2, 3]]),
        p_hit=1.0,
        range_sigma=0.02,
        label=CLASS_ID["ground"],
    )


@functools.lru_cache(maxsize=4)
def _library(path: str) -> PrimitiveLibrary:
    return PrimitiveLibrary.load(path)


def path_frame(waypoints: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) and unit tangents (N, 2) at arc lengths ``s`` (m) along a polyline (W, 2+)."""
    xy = waypoints[:, :2]
    steps = np.diff(xy, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    cumulative = np.r_[0.0, np.cumsum(lengths)]
    segment = np.clip(np.searchsorted(cumulative, s, side="right") - 1, 0, len(lengths) - 1)
    t = (s - cumulative[segment]) / lengths[segment]
    return xy[segment] + t[:, None] * steps[segment], steps[segment] / lengths[segment, None]


def check_classes(scene_spec: SceneSpec, library: PrimitiveLibrary) -> None:
    """Raise :class:`SpecError` when a random scene's class has no primitive in its library."""
    missing = [c for c in scene_spec.random.classes if not library.of_class(c)]
    if missing:
        raise SpecError(
            f"scene {scene_spec.name!r}: the library {scene_spec.library} has no primitive of class {missing}; "
            f"it has {sorted({p.class_name for p in library.primitives})}"
        )


def random_objects(scene_spec: SceneSpec, library: PrimitiveLibrary, height: Callable, rng) -> list[dict]:
    """Annotation objects drawn along the trajectory: class uniform, primitive uniform within it, yaw uniform.

    Objects stand on the ground (box bottom at the ground height under the centroid), lie between
    ``lateral`` bounds from the path on either side, and do not overlap (horizontal box circles).
    """
    options = scene_spec.random
    check_classes(scene_spec, library)
    waypoints = np.asarray([w[:2] for w in scene_spec.trajectory.waypoints], float)
    length = float(np.linalg.norm(np.diff(waypoints, axis=0), axis=1).sum())
    placed: list[tuple[np.ndarray, float]] = []
    objects = []
    for _ in range(50 * options.count):
        if len(objects) == options.count:
            break
        primitive = rng.choice(library.of_class(str(rng.choice(options.classes))))
        radius = 0.5 * float(np.hypot(*primitive.extents[:2]))
        point, tangent = path_frame(waypoints, np.array([rng.uniform(0, length)]))
        side = rng.choice([-1.0, 1.0])
        offset = rng.uniform(options.lateral[0] + radius, max(options.lateral[1], options.lateral[0] + radius) + radius)
        xy = point[0] + side * offset * np.array([-tangent[0, 1], tangent[0, 0]])
        if _distance_to_path(waypoints, xy) < options.lateral[0] + radius:
            continue
        if any(np.linalg.norm(xy - other) < radius + r for other, r in placed):
            continue
        placed.append((xy, radius))
        z = float(height(xy[0], xy[1])) - float(primitive.box_lo[2])
        objects.append(
            {
                "class": primitive.class_name,
                "center": [float(xy[0]), float(xy[1]), z],
                "yaw": float(rng.uniform(-np.pi, np.pi)),
                "extents": [float(v) for v in primitive.extents],
            }
        )
    return objects


def _distance_to_path(waypoints: np.ndarray, xy: np.ndarray) -> float:
    a, b = waypoints[:-1], waypoints[1:]
    t = np.clip(np.einsum("ij,ij->i", xy - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * (b - a) - xy, axis=1)))


def hybrid_scene(spec: DatasetSpec, scene_index: int, variant: int) -> SceneInstance:
    """An annotation (from a file, or drawn at random) filled with the library's primitives."""
    scene_spec = spec.scenes[scene_index]
    library = _library(str(spec.resolve(scene_spec.library)))
    waypoints = np.asarray([(*w[:2], w[2] if len(w) > 2 else 0.0) for w in scene_spec.trajectory.waypoints], float)
    if scene_spec.annotation is not None:
        objects, ground = load_annotation(spec.resolve(scene_spec.annotation))
    else:
        ground = read_mesh_ply(spec.resolve(scene_spec.ground)) if scene_spec.ground is not None else None
    if ground is None:
        ground = flat_ground(waypoints)
    height = height_function(ground)
    if scene_spec.random is not None:
        rng = np.random.default_rng([spec.seed, scene_index, variant])
        objects = random_objects(scene_spec, library, height, rng)
    model = compose_scene(objects, library, ground)
    sets = hybrid_element_sets(model)
    boxes, shape_instance = [], {}
    skipped = set(model.info["skipped"])
    for i, obj in enumerate(objects):
        if i in skipped:
            continue
        primitive = library.best_match(obj["class"], obj["extents"])
        rotation = rotation_z(float(obj["yaw"]))
        center = np.asarray(obj["center"], float) + rotation @ ((primitive.box_lo + primitive.box_hi) / 2)
        boxes.append(Box3D(obj["class"], i + 1, center, primitive.extents.astype(float), float(obj["yaw"])))
        shape_instance[f"{obj['class']}_{i}"] = i + 1
    scene = scene_dict(sets)
    for key, elements in sets.items():
        if isinstance(elements, EllipsoidElements):
            colour = ROCK if key.startswith("rock") else FOLIAGE
            scene[key] = {
                **ellipsoids_dict(elements),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": colour}},
            }
    scene.update(LIGHTS)
    label_names = dict(enumerate(CLASS_NAMES))
    return SceneInstance(load_scene(scene), boxes, shape_instance, label_names, height)


def build_scene(spec: DatasetSpec, scene_index: int, variant: int) -> SceneInstance:
    """The scene of ``spec.scenes[scene_index]`` in variant ``variant``, checked for unnamed labels.

    Raises:
        SpecError: an XML object names an unknown shape, a random class is not in the library, or an
            element label has no class name (add it under the scene's ``labels:``).
        SceneError: the scene cannot be loaded.
    """
    scene_spec = spec.scenes[scene_index]
    instance = xml_scene(spec, scene_spec) if scene_spec.xml is not None else hybrid_scene(spec, scene_index, variant)
    table = ElementTable.from_scene(instance.scene)
    instance.shape_ids = list(table.shape_ids)
    instance.instance_of_shape = instance_by_registry(instance.scene, instance.shape_instance)
    unnamed = sorted(set(np.unique(np.asarray(table.label)).tolist()) - set(instance.label_names))
    if unnamed:
        raise SpecError(
            f"scene {scene_spec.name!r}: element labels {unnamed} have no class name; add each under the "
            f"scene's labels: with the class its elements belong to, e.g. labels: {{{unnamed[0]}: vegetation}}"
        )
    if not instance.scene.shapes():
        raise SceneError(f"scene {scene_spec.name!r} has no shapes")
    return instance


def check_scenes(spec: DatasetSpec, scene_indices: list[int]) -> None:
    """Find, before any frame is rendered, what would make every frame of a scene fail.

    XML scenes are loaded and checked as :func:`build_scene` does (object shapes, named labels);
    annotation files are read; random scenes' classes are looked up in their library. Hybrid scenes
    are not composed here: that is each frame's work.

    Raises:
        SpecError: as :func:`build_scene`, or a random class the library lacks.
        SceneError: an XML scene, annotation or library that cannot be read.
    """
    for index in scene_indices:
        scene_spec = spec.scenes[index]
        if scene_spec.xml is not None:
            build_scene(spec, index, 0)
            continue
        library = _library(str(spec.resolve(scene_spec.library)))
        if scene_spec.annotation is not None:
            load_annotation(spec.resolve(scene_spec.annotation))
        else:
            check_classes(scene_spec, library)
