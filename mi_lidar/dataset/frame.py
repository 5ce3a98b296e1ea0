"""One dataset frame: the ego pose, the Lidar points with labels, the camera images, written in KITTI layout.

Frame ``k`` depends only on the spec and ``k``: its random streams are seeded with
``SeedSequence([spec.seed, k])`` (one Lidar seed per rig Lidar, one camera seed), its scene variant
with ``[spec.seed, scene, variant]``. Any worker, in any order, writes the same bytes.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.dataset.occlusion import hidden_fractions, occlusion_level
from mi_lidar.dataset.rig import Rig
from mi_lidar.dataset.scenes import Box3D, SceneInstance, build_scene, path_frame
from mi_lidar.dataset.spec import DatasetSpec
from mi_lidar.scene.simulation import simulate

# SemanticKITTI ids of class names (semantic-kitti.yaml); off-road thesis classes get 100 + class id.
SEMANTIC_IDS = {
    "unlabeled": 0,
    "none": 0,
    "car": 10,
    "bicycle": 11,
    "truck": 18,
    "person": 30,
    "road": 40,
    "parking": 44,
    "sidewalk": 48,
    "building": 50,
    "fence": 51,
    "vegetation": 70,
    "trunk": 71,
    "terrain": 72,
    "pole": 80,
    "traffic-sign": 81,
    "ground": 101,
    "grass": 102,
    "rock": 103,
    "low_shrub": 104,
    "small_shrub": 105,
    "medium_shrub": 106,
    "large_shrub": 107,
    "small_tree": 108,
    "medium_tree": 109,
    "large_tree": 110,
}
INTENSITY_NOTE = (
    "velodyne/*.bin intensity column: the simulated intensity in the sensor's integer scale "
    "(mi_lidar.core.intensity: element reflectivity, range, incidence, per-beam gain and noise)"
)


@dataclass
class Frame:
    """What frame ``index`` holds before it is written.

    Attributes:
        index: frame number. scene: scene name. ego_to_world: (4, 4) ego pose.
        points: (N, 3) float32 returns of all Lidars in the first Lidar's frame, m.
        intensity: (N,) float32. semantic, instance: (N,) uint16 per point.
        images: one (H, W, 3) linear RGB float32 image per rig camera.
        boxes: labelled objects of the scene.
        hidden: hidden fraction of each box seen by camera 0, by instance id (NaN: unknown; see
            :mod:`.occlusion`).
        scene_seconds: wall time spent loading the scene for this frame, s (0 when it was cached).
    """

    index: int
    scene: str
    ego_to_world: np.ndarray
    points: np.ndarray
    intensity: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    images: list[np.ndarray]
    boxes: list[Box3D]
    hidden: dict[int, float] = field(default_factory=dict)
    scene_seconds: float = 0.0


def frame_seeds(seed: int, index: int, count: int) -> list[int]:
    """``count`` independent 31-bit seeds of frame ``index``."""
    return [int(s) for s in np.random.SeedSequence([seed, index]).generate_state(count) & 0x7FFFFFFF]


def ego_pose(spec: DatasetSpec, scene: SceneInstance, scene_index: int, step: int, steps: int) -> np.ndarray:
    """(4, 4) ego-to-world pose at step ``step`` of ``steps`` evenly spaced along the scene's trajectory.

    Heading follows the path's tangent; height is the ground's (hybrid scenes with ``follow_ground``)
    or the waypoints' z interpolated along the path (m).
    """
    trajectory = spec.scenes[scene_index].trajectory
    waypoints = np.asarray([(*w[:2], w[2] if len(w) > 2 else 0.0) for w in trajectory.waypoints], float)
    cumulative = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(waypoints[:, :2], axis=0), axis=1))]
    s = cumulative[-1] * (step + 0.5) / steps
    (xy,), (tangent,) = path_frame(waypoints, np.array([s]))
    if trajectory.follow_ground and scene.ground_height is not None:
        z = float(scene.ground_height(xy[0], xy[1]))
    else:
        z = float(np.interp(s, cumulative, waypoints[:, 2]))
    pose = np.eye(4)
    pose[:3, :3] = [[tangent[0], -tangent[1], 0], [tangent[1], tangent[0], 0], [0, 0, 1]]
    pose[:3, 3] = [xy[0], xy[1], z]
    return pose


def semantic_table(spec: DatasetSpec) -> dict[str, int]:
    """Class name -> SemanticKITTI id: :data:`SEMANTIC_IDS` updated by the spec's ``output.semantic_ids``."""
    return {**SEMANTIC_IDS, **spec.output.semantic_ids}


def render_frame(spec: DatasetSpec, rig: Rig, index: int, scenes: dict) -> Frame:
    """Simulate frame ``index``: every rig Lidar and camera at the frame's ego pose.

    Args:
        spec: the dataset spec. rig: its rig. index: frame number.
        scenes: cache ``{(scene, variant): SceneInstance}`` reused across frames of one process.
    """
    from mi_lidar.core.errors import SpecError
    from mi_lidar.scene.camera import render_camera

    scene_index, variant, step, steps = spec.locate(index)
    key = (scene_index, variant)
    start = time.perf_counter()
    if key not in scenes:
        scenes.clear()
        scenes[key] = build_scene(spec, scene_index, variant)
    scene_seconds = time.perf_counter() - start
    scene = scenes[key]
    ego = ego_pose(spec, scene, scene_index, step, steps)
    seeds = frame_seeds(spec.seed, index, len(rig.lidars) + 1)
    table = semantic_table(spec)
    world_to_reference = np.linalg.inv(ego @ rig.lidars[0].to_ego)
    parts = []
    for lidar, seed in zip(rig.lidars, seeds):
        log = simulate(scene.scene, lidar.pattern, poses=ego @ lidar.to_ego, seed=seed, model=lidar.model)
        hit = log.hit[0]
        world = log.points_world()[0][hit]
        labels = np.asarray(log.attributes["label"][0][hit]).astype(np.int64)
        shapes = np.asarray(log.attributes["shape_id"][0][hit]).astype(np.int64)
        intensity = log.attributes.get("intensity")
        names = [scene.label_names.get(int(v)) for v in np.unique(labels)]
        unknown = sorted({n for n in names if n not in table})
        if unknown:
            raise SpecError(
                f"classes {unknown} have no SemanticKITTI id; add them under output.semantic_ids, e.g. {unknown[0]}: 99"
            )
        semantic = np.array([table[scene.label_names[int(v)]] for v in labels], dtype=np.uint16)
        shape_instance = np.array([scene.shape_instance.get(s, 0) for s in scene.shape_ids], dtype=np.uint16)
        parts.append(
            (
                (np.c_[world, np.ones(len(world))] @ world_to_reference.T)[:, :3],
                np.zeros(len(world)) if intensity is None else np.asarray(intensity[0][hit]),
                semantic,
                # shape -1: a return of no element (the density's spurious readings): instance 0
                np.where(shapes >= 0, shape_instance[np.maximum(shapes, 0)], 0).astype(np.uint16)
                if len(shape_instance)
                else np.zeros(len(world), np.uint16),
            )
        )
    images = [render_camera(scene.scene, camera.at(ego), spp=spec.output.spp, seed=seeds[-1]) for camera in rig.cameras]
    hidden = hidden_fractions(scene.scene, rig.cameras[0].at(ego), scene.boxes, scene.instance_of_shape)
    return Frame(
        index=index,
        scene=spec.scenes[scene_index].name,
        ego_to_world=ego,
        points=np.concatenate([p[0] for p in parts]).astype(np.float32),
        intensity=np.concatenate([p[1] for p in parts]).astype(np.float32),
        semantic=np.concatenate([p[2] for p in parts]),
        instance=np.concatenate([p[3] for p in parts]),
        images=images,
        boxes=scene.boxes,
        hidden=hidden,
        scene_seconds=scene_seconds,
    )


def kitti_objects(frame: Frame, rig: Rig) -> list[dict]:
    """``label_2`` rows of the frame's boxes in front of the reference camera whose projection meets the image.

    ``truncated`` is the fraction of the projected box outside the image; ``occluded`` is KITTI's level
    (0 fully visible, 1 partly occluded, 2 largely occluded, 3 unknown) of the object's hidden fraction
    as camera 0 sees it (:mod:`.occlusion`); boxes reaching behind the camera plane are left out.
    Each row also carries the ``instance`` id and the ``hidden`` fraction (the manifest keeps them).
    """
    camera = rig.cameras[0].at(frame.ego_to_world)
    world_to_camera = camera.world_to_opencv
    area = lambda b: max(b[2] - b[0], 0.0) * max(b[3] - b[1], 0.0)  # noqa: E731
    rows = []
    for box in frame.boxes:
        uv, depth, _ = camera.project(box.corners())
        if np.any(depth <= 0.1):
            continue
        full = np.r_[uv.min(0), uv.max(0)]
        clipped = np.clip(full, 0, [camera.width, camera.height] * 2)
        if area(clipped) <= 0:
            continue
        bottom = box.center - [0, 0, box.size[2] / 2]
        x, y, z = (world_to_camera @ np.r_[bottom, 1.0])[:3]
        heading = world_to_camera[:3, :3] @ [np.cos(box.yaw), np.sin(box.yaw), 0.0]
        rotation_y = float(np.arctan2(-heading[2], heading[0]))
        alpha = (rotation_y - np.arctan2(x, z) + np.pi) % (2 * np.pi) - np.pi
        truncated = 1.0 - area(clipped) / max(area(full), 1e-9)
        rows.append(
            {
                "type": box.class_name,
                "truncated": float(np.clip(truncated, 0, 1)),
                "occluded": occlusion_level(frame.hidden.get(box.instance, float("nan"))),
                "alpha": float(alpha),
                "left": clipped[0],
                "top": clipped[1],
                "right": clipped[2],
                "bottom": clipped[3],
                "height": box.size[2],
                "width": box.size[1],
                "length": box.size[0],
                "x": x,
                "y": y,
                "z": z,
                "rotation_y": rotation_y,
                "instance": box.instance,
                "hidden": frame.hidden.get(box.instance, float("nan")),
            }
        )
    return rows


def write_frame(out: Path, frame: Frame, rig: Rig, overlays: bool) -> dict:
    """Write frame files atomically and return its manifest record (file digests, counts, objects).

    Files: ``velodyne/K.bin``, ``labels/K.label``, ``image_{2+i}/K.png`` per camera, ``calib/K.txt``,
    ``label_2/K.txt`` and, with ``overlays``, ``overlay/K_<camera>.png`` (``K`` = 6-digit frame number).
    """
    from mi_lidar.io.kitti import write_kitti_bin
    from mi_lidar.io.kitti_labels import write_kitti_calib, write_kitti_labels, write_semantic_labels
    from mi_lidar.io.preview import overlay_png, rgb_png

    name = f"{frame.index:06d}"
    objects = kitti_objects(frame, rig)
    files = [
        write_kitti_bin(out / "velodyne" / f"{name}.bin", frame.points, frame.intensity),
        write_semantic_labels(out / "labels" / f"{name}.label", frame.semantic, frame.instance),
        write_kitti_calib(out / "calib" / f"{name}.txt", rig.calibration()),
        write_kitti_labels(out / "label_2" / f"{name}.txt", objects),
    ]
    lidar_to_world = frame.ego_to_world @ rig.lidars[0].to_ego
    points_world = frame.points.astype(np.float64) @ lidar_to_world[:3, :3].T + lidar_to_world[:3, 3]
    for i, (camera, image) in enumerate(zip(rig.cameras, frame.images)):
        files.append(rgb_png(out / f"image_{i + 2}" / f"{name}.png", image))
        if overlays:
            uv, depth, visible = camera.at(frame.ego_to_world).project(points_world)
            files.append(
                overlay_png(
                    out / "overlay" / f"{name}_{camera.name}.png",
                    image,
                    uv[visible],
                    depth[visible],
                    title=f"frame {frame.index} ({frame.scene}), {camera.name}",
                )
            )
    return {
        "frame": frame.index,
        "scene": frame.scene,
        "ego_to_world": frame.ego_to_world.tolist(),
        "reference_camera_to_world": (frame.ego_to_world @ rig.cameras[0].optical_to_ego).tolist(),
        "points": int(len(frame.points)),
        "objects": [
            {
                "instance": o["instance"],
                "type": o["type"],
                "occluded": o["occluded"],
                "hidden": None if np.isnan(o["hidden"]) else round(o["hidden"], 3),
            }
            for o in objects
        ],
        "files": {str(Path(f).relative_to(out)): file_digest(f) for f in files},
    }


def file_digest(path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
