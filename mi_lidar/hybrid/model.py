"""In-memory hybrid geometric model: ground triangles and Gaussian ellipsoids (thesis 4.3.1.2).

Every element carries a hit probability ``p_hit`` (Bernoulli pass-through), a class ``label``,
an ``instance`` id and the ``block`` it was fitted in. Triangles also carry ``range_sigma`` (m);
an ellipsoid's return is drawn from its Gaussian restricted to the ray.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class GroundMesh:
    """Triangle elements.

    Attributes:
        vertices: (V, 3) float64, m.
        faces: (F, 3) int64.
        p_hit: (F,) hit probability.
        range_sigma: (F,) range noise standard deviation, m.
        label, instance, block: (F,) int32.
    """

    vertices: np.ndarray
    faces: np.ndarray
    p_hit: np.ndarray | None = None
    range_sigma: np.ndarray | None = None
    label: np.ndarray | None = None
    instance: np.ndarray | None = None
    block: np.ndarray | None = None

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, np.int64).reshape(-1, 3)
        f = len(self.faces)
        fill = lambda a, v, dt: np.full(f, v, dt) if a is None else np.broadcast_to(np.asarray(a, dt), (f,)).copy()
        self.p_hit = fill(self.p_hit, 1.0, np.float64)
        self.range_sigma = fill(self.range_sigma, 0.0, np.float64)
        self.label = fill(self.label, 1, np.int32)
        self.instance = fill(self.instance, 0, np.int32)
        self.block = fill(self.block, 0, np.int32)

    def __len__(self) -> int:
        return len(self.faces)

    @staticmethod
    def concat(parts: list[GroundMesh]) -> GroundMesh:
        """Concatenate meshes (vertex indices are shifted)."""
        parts = [p for p in parts if len(p)] or [GroundMesh(np.zeros((0, 3)), np.zeros((0, 3)))]
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])
        return GroundMesh(
            cat("vertices"),
            np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
            cat("p_hit"),
            cat("range_sigma"),
            cat("label"),
            cat("instance"),
            cat("block"),
        )

    def subset(self, mask: np.ndarray) -> GroundMesh:
        """The faces where ``mask`` (F,) is True (vertices are kept)."""
        return GroundMesh(
            self.vertices,
            self.faces[mask],
            self.p_hit[mask],
            self.range_sigma[mask],
            self.label[mask],
            self.instance[mask],
            self.block[mask],
        )


@dataclass
class EllipsoidSet:
    """Gaussian ellipsoid elements.

    Attributes:
        means: (N, 3) float64, m.
        covs: (N, 3, 3) float64 covariances, m^2.
        p_hit: (N,) hit probability.
        label, instance, block: (N,) int32.
    """

    means: np.ndarray
    covs: np.ndarray
    p_hit: np.ndarray | None = None
    label: np.ndarray | None = None
    instance: np.ndarray | None = None
    block: np.ndarray | None = None

    def __post_init__(self):
        self.means = np.asarray(self.means, np.float64).reshape(-1, 3)
        self.covs = np.asarray(self.covs, np.float64).reshape(-1, 3, 3)
        n = len(self.means)
        fill = lambda a, v, dt: np.full(n, v, dt) if a is None else np.broadcast_to(np.asarray(a, dt), (n,)).copy()
        self.p_hit = fill(self.p_hit, 1.0, np.float64)
        self.label = fill(self.label, 0, np.int32)
        self.instance = fill(self.instance, 0, np.int32)
        self.block = fill(self.block, 0, np.int32)

    def __len__(self) -> int:
        return len(self.means)

    @staticmethod
    def concat(parts: list[EllipsoidSet]) -> EllipsoidSet:
        """Concatenate ellipsoid sets."""
        parts = [p for p in parts if len(p)] or [EllipsoidSet(np.zeros((0, 3)), np.zeros((0, 3, 3)))]
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])
        return EllipsoidSet(cat("means"), cat("covs"), cat("p_hit"), cat("label"), cat("instance"), cat("block"))

    def subset(self, mask: np.ndarray) -> EllipsoidSet:
        """The ellipsoids selected by boolean or index array ``mask``."""
        return EllipsoidSet(
            self.means[mask], self.covs[mask], self.p_hit[mask], self.label[mask], self.instance[mask], self.block[mask]
        )

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> EllipsoidSet:
        """The set moved by ``x -> rotation @ x + translation`` ((3, 3), (3,) m)."""
        r = np.asarray(rotation, float)
        return EllipsoidSet(
            self.means @ r.T + translation, r @ self.covs @ r.T, self.p_hit, self.label, self.instance, self.block
        )

    def axes(self, min_sigma: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """Principal standard deviations (N, 3) (m, floored at ``min_sigma``) and quaternions (N, 4) (x, y, z, w)."""
        if len(self) == 0:
            return np.zeros((0, 3)), np.zeros((0, 4))
        w, v = np.linalg.eigh(self.covs)
        v[np.linalg.det(v) < 0, :, 0] *= -1
        return np.sqrt(np.maximum(w, min_sigma**2)), Rotation.from_matrix(v).as_quat()

    @staticmethod
    def from_axes(means, scales, quaternions, **attributes) -> EllipsoidSet:
        """Build a set from (N, 3) means, (N, 3) standard deviations (m) and (N, 4) (x, y, z, w) quaternions."""
        r = Rotation.from_quat(np.asarray(quaternions, float)).as_matrix() if len(means) else np.zeros((0, 3, 3))
        variances = np.asarray(scales, float) ** 2
        covs = np.einsum("nij,nj,nkj->nik", r, variances, r)
        return EllipsoidSet(means, covs, **attributes)


@dataclass
class HybridModel:
    """A hybrid geometric scene: ground triangles, ellipsoids and the ellipsoid extent (sigmas).

    ``origin`` (3,) m is the world position of the frame the elements are given in: zero, or the
    local origin of a scene fitted to georeferenced data (:mod:`mi_lidar.core.frames`), which the
    scene XML places with a ``translate``.
    """

    ground: GroundMesh
    ellipsoids: EllipsoidSet
    extent: float = 3.5
    info: dict = field(default_factory=dict)
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
