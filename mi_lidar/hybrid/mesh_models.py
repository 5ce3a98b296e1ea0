"""Stock mesh models per class: the primitive library of the mesh-model baseline (thesis 4.3.2).

The thesis's baseline took its primitives from open-source tree and shrub meshes (TurboSquid),
"subsampled, transformed, scaled and sorted into appropriate classes" (fig. 4.17, bottom). Our
stand-ins for those downloaded models are objects of the synthetic world's own generator
(:func:`.world.object_mesh`: a trunk, branch prisms and many leaf triangles for trees and shrubs,
a bumpy flattened icosphere for rocks), drawn from random streams no world uses: model ``k`` of
class ``c`` is drawn with ``numpy.random.default_rng([LIBRARY_SEED, c, k])`` while worlds are
seeded with one integer. Each class gets ``per_class`` models whose heights (rock sizes) are
spread evenly over the class's range. The models are built like the worlds' objects but are not
the annotated objects, so a model fits an object as well as a stock model of the right class and
about the right size would.

Model frame (as for the data-driven primitives of :mod:`.primitives`, whose origin is the
centroid of an object's returns): the origin is the area-weighted centroid of the faces above
the model's base (the expected centroid of points drawn uniformly on the part above the
ground), x along the generator's wider crown axis, z up. The box is the vertices' bounding box
with its bottom raised to the base (the buried foot of a trunk or rock is not seen).

Scene objects are built as :func:`.compose.compose_scene` builds ours: per annotated object, the
model of its class whose box extents are closest (Euclidean norm), rotated by the object's yaw
and moved to its centre, never rescaled.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import SceneError
from mi_lidar.hybrid.classes import CLASS_NAMES, OBJECT_CLASSES, class_id
from mi_lidar.hybrid.primitives import closest_extents, rotation_z
from mi_lidar.hybrid.world import CLASS_SHAPES, ROCK_SIZE, object_mesh

LIBRARY_SEED = 4317  # first word of every model's seed sequence


@dataclass
class MeshModel:
    """One opaque stock model in its model frame.

    Attributes:
        id: ``<class>_<index>``.
        label: class id.
        vertices: (V, 3) float64 positions in the model frame, m.
        faces: (F, 3) int64 vertex indices.
        extents: (3,) side lengths of the box above the base, m.
        size: height (trees, shrubs) or largest half-axis (rocks) it was generated with, m.
    """

    id: str
    label: int
    vertices: np.ndarray
    faces: np.ndarray
    extents: np.ndarray
    size: float

    def placed(self, yaw: float, center) -> np.ndarray:
        """(V, 3) vertices rotated by ``yaw`` (rad) about z and moved to ``center`` (3,), m."""
        return self.vertices @ rotation_z(yaw).T + np.asarray(center, float)


def model_from_mesh(model_id: str, label: int, vertices: np.ndarray, faces: np.ndarray, size: float) -> MeshModel:
    """Move a generator mesh standing on the origin into the model frame (see module docstring).

    Args:
        model_id: the model's id. label: class id.
        vertices: (V, 3) positions, m, the base at z = 0. faces: (F, 3) vertex indices.
        size: height or rock half-axis the mesh was generated with, m.
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    centroid = tri.mean(axis=1)
    above = centroid[:, 2] > 0
    origin = np.average(centroid[above], axis=0, weights=area[above])
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    lo[2] = max(lo[2], 0.0)
    return MeshModel(model_id, label, vertices - origin, faces, hi - lo, float(size))


class MeshModelLibrary:
    """Stock mesh models of the object classes, with closest-box choice and a preview."""

    def __init__(self, models: list[MeshModel]):
        self.models = list(models)

    def __len__(self) -> int:
        return len(self.models)

    @classmethod
    def generate(cls, per_class: int = 4, seed: int = LIBRARY_SEED) -> MeshModelLibrary:
        """``per_class`` generator models of every object class (rock, shrubs, trees).

        Args:
            per_class: models per class; their sizes are the midpoints of ``per_class`` equal
                slices of the class's height range (rock: half-axis range).
            seed: first word of each model's seed sequence ``[seed, class id, index]``.
        """
        models = []
        for label in OBJECT_CLASSES:
            name = CLASS_NAMES[label]
            lo, hi = ROCK_SIZE if name == "rock" else CLASS_SHAPES[name][0]
            for k in range(per_class):
                size = lo + (hi - lo) * (k + 0.5) / per_class
                vertices, faces = object_mesh(name, size, np.random.default_rng([seed, label, k]))
                models.append(model_from_mesh(f"{name}_{k}", label, vertices, faces, size))
        return cls(models)

    def best_match(self, label: int | str, extents) -> MeshModel:
        """The model of class ``label`` whose box extents are closest (Euclidean) to ``extents`` (3,) m."""
        c = class_id(label)
        candidates = [m for m in self.models if m.label == c]
        if not candidates:
            have = sorted({CLASS_NAMES[m.label] for m in self.models})
            raise SceneError(
                f"the mesh-model library has no {CLASS_NAMES[c]!r}; it holds {have}. "
                "Generate it with MeshModelLibrary.generate()."
            )
        return candidates[closest_extents([m.extents for m in candidates], extents)]

    def preview(self, path) -> Path:
        """Save a PNG of side views (x-z) of every model, one row per class, titled with its box extents.

        Args:
            path: output ``.png``.
        """
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.collections import PolyCollection

        labels = sorted({m.label for m in self.models})
        cols = max(sum(m.label == c for m in self.models) for c in labels)
        fig, axes = plt.subplots(
            len(labels), cols, figsize=(2.2 * cols, 2.2 * len(labels)), squeeze=False, layout="constrained"
        )
        for row, c in zip(axes, labels):
            models = [m for m in self.models if m.label == c]
            for ax, m in zip(row, models):
                ax.add_collection(
                    PolyCollection(
                        m.vertices[m.faces][:, :, [0, 2]], facecolor="forestgreen", edgecolor="none", alpha=0.6
                    )
                )
                lo, hi = m.vertices.min(axis=0) - 0.3, m.vertices.max(axis=0) + 0.3
                ax.set_xlim(lo[0], hi[0])
                ax.set_ylim(lo[2], hi[2])
                ax.set_aspect("equal")
                ax.set_title(
                    f"{m.id}: {len(m.faces)} faces\nbox {m.extents[0]:.1f} x {m.extents[1]:.1f} x {m.extents[2]:.1f} m",
                    fontsize=7,
                )
                ax.tick_params(labelsize=6)
            for ax in row[len(models) :]:
                ax.axis("off")
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=80)
        plt.close(fig)
        return Path(path)
