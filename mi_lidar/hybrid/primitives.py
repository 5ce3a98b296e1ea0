"""Scene primitives (thesis 4.3.1.4): labelled objects moved to the identity pose, in a library.

Object pose: translation = centroid of the segment's points; rotation about z only, the local
x axis being the horizontal principal axis closest to the sensor velocity at the object. The
oriented box spans the points in that frame. The object model is the set of ellipsoids whose
mean lies in the box; it is stored transformed to identity with its class and box extents.

On disk a library is a folder with ``library.json`` (index) and one ``<id>.npz`` per primitive.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_lidar.core.atomic import atomic_path
from mi_lidar.core.errors import NPZ_MEMBER_ERRORS, SceneError, numpy_file_problem, unreadable
from mi_lidar.core.strict_json import write_json
from mi_lidar.hybrid.classes import CLASS_NAMES, class_id
from mi_lidar.hybrid.model import EllipsoidSet, HybridModel
from mi_lidar.hybrid.segments import Segment

LIBRARY_FORMAT, LIBRARY_VERSION = "mi-lidar-primitives", 1  # library.json's format and version


def rotation_z(yaw: float) -> np.ndarray:
    """(3, 3) rotation by ``yaw`` rad about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def closest_extents(candidates, extents) -> int:
    """Index of the box in ``candidates`` (K, 3) closest to ``extents`` (3,) in Euclidean norm, m."""
    d = np.linalg.norm(np.asarray(candidates, float).reshape(-1, 3) - np.asarray(extents, float), axis=1)
    return int(np.argmin(d))


def object_pose(points: np.ndarray, velocity_xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid (3,) m and yaw (rad) of an object's (M, 3) points; ``velocity_xy`` (2,) picks the x axis."""
    center = points.mean(axis=0)
    xy = points[:, :2] - center[:2]
    _, vecs = np.linalg.eigh(np.cov(xy.T) if len(points) > 2 else np.eye(2))
    v = np.asarray(velocity_xy, float)
    v = v / max(np.linalg.norm(v), 1e-12)
    axis = vecs[:, np.argmax(np.abs(vecs.T @ v))]
    if axis @ v < 0:
        axis = -axis
    return center, float(np.arctan2(axis[1], axis[0]))


def oriented_box(points: np.ndarray, center: np.ndarray, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Box bounds (lo (3,), hi (3,)) of the points in the object frame (centroid, yaw), m."""
    local = (points - center) @ rotation_z(yaw)
    return local.min(axis=0), local.max(axis=0)


@dataclass
class Primitive:
    """A primitive pi = (c, M): class id, ellipsoids at identity and box bounds (m)."""

    id: str
    label: int
    ellipsoids: EllipsoidSet
    box_lo: np.ndarray
    box_hi: np.ndarray
    source: dict = field(default_factory=dict)

    @property
    def extents(self) -> np.ndarray:
        """(3,) box side lengths, m."""
        return np.asarray(self.box_hi) - np.asarray(self.box_lo)

    @property
    def class_name(self) -> str:
        return CLASS_NAMES[self.label]


def sensor_velocity_at(poses: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(2,) horizontal travel direction of the sensor at the pose nearest to ``xy`` (m)."""
    pos = poses[:, :2, 3]
    i = int(np.argmin(np.sum((pos - xy) ** 2, axis=1)))
    a, b = max(i - 1, 0), min(i + 1, len(pos) - 1)
    v = pos[b] - pos[a]
    return v if np.linalg.norm(v) > 0 else np.array([1.0, 0.0])


def extract_primitives(
    model: HybridModel,
    points: np.ndarray,
    segments: list[Segment],
    poses: np.ndarray,
    source: str = "",
    min_ellipsoids: int = 1,
) -> list[Primitive]:
    """Primitives of labelled segments.

    Args:
        model: fitted model (its ellipsoids form the object models).
        points: (N, 3) world points the segments index, m.
        segments: labelled segments.
        poses: (S, 4, 4) sensor poses (for the velocity that orients objects).
        source: name of the scene recorded in each primitive.
        min_ellipsoids: segments with fewer ellipsoids in their box are skipped.
    """
    out = []
    e = model.ellipsoids
    for seg in segments:
        pts = points[seg.index]
        center, yaw = object_pose(pts, sensor_velocity_at(poses, pts[:, :2].mean(axis=0)))
        lo, hi = oriented_box(pts, center, yaw)
        rot = rotation_z(yaw)
        local = (e.means - center) @ rot
        inside = np.all((local >= lo) & (local <= hi), axis=1)
        if inside.sum() < min_ellipsoids:
            continue
        ell = e.subset(inside).transformed(rot.T, -rot.T @ center)
        ell.label[:] = seg.label
        ell.instance[:] = 0
        ell.block[:] = 0
        out.append(
            Primitive(
                f"{source or 'scene'}_{CLASS_NAMES[seg.label]}_{seg.id}",
                seg.label,
                ell,
                lo,
                hi,
                {"scene": source, "segment": int(seg.id), "patch": bool(seg.patch), "n_points": int(len(pts))},
            )
        )
    return out


class PrimitiveLibrary:
    """A set of primitives with save, load, list, best match and preview."""

    def __init__(self, primitives: list[Primitive] | None = None):
        self.primitives = list(primitives or [])

    def __len__(self) -> int:
        return len(self.primitives)

    def add(self, primitives: list[Primitive]) -> None:
        """Append primitives."""
        self.primitives.extend(primitives)

    def of_class(self, label: int | str) -> list[Primitive]:
        """Primitives of one class (name or id)."""
        c = class_id(label)
        return [p for p in self.primitives if p.label == c]

    def best_match(self, label: int | str, extents: np.ndarray) -> Primitive:
        """The primitive of class ``label`` whose box extents are closest (Euclidean) to ``extents`` (m)."""
        cands = self.of_class(label)
        if not cands:
            have = sorted({p.class_name for p in self.primitives})
            raise SceneError(
                f"the primitive library has no {CLASS_NAMES[class_id(label)]!r}; it holds {have}. "
                "Extract primitives from a log that contains this class."
            )
        return cands[closest_extents([p.extents for p in cands], extents)]

    def rows(self) -> list[dict]:
        """One summary dict per primitive (id, class, ellipsoids, extents in m, source)."""
        return [
            {
                "id": p.id,
                "class": p.class_name,
                "ellipsoids": len(p.ellipsoids),
                "extents": [round(float(x), 3) for x in p.extents],
                "source": p.source,
            }
            for p in self.primitives
        ]

    def save(self, folder) -> Path:
        """Write ``library.json`` and one ``.npz`` per primitive to ``folder``; return the index path."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        index = []
        for p in self.primitives:
            e = p.ellipsoids
            with atomic_path(folder / f"{p.id}.npz") as tmp:
                np.savez_compressed(tmp, means=e.means, covs=e.covs, p_hit=e.p_hit, box_lo=p.box_lo, box_hi=p.box_hi)
            index.append(
                {"id": p.id, "label": int(p.label), "class": p.class_name, "file": f"{p.id}.npz", "source": p.source}
            )
        # the index last, so that it only ever names whole files
        return write_json(
            folder / "library.json", {"format": LIBRARY_FORMAT, "version": LIBRARY_VERSION, "primitives": index}
        )

    @classmethod
    def load(cls, folder) -> PrimitiveLibrary:
        """Read a library written by :meth:`save`.

        Raises:
            SceneError: naming the file: no or unreadable ``library.json``, an index entry without
                ``id``/``label``/``file``, or a primitive file that is missing, damaged or holds
                arrays of the wrong shapes or non-finite values.
        """
        folder = Path(folder)
        path = folder / "library.json"
        if not path.is_file():
            raise SceneError(f"{folder}: no library.json; create a library with mi-lidar primitives extract")
        try:
            index = json.loads(path.read_text())
            items = index["primitives"]
            entries = [(str(item["id"]), class_id(int(item["label"])), str(item["file"]), item) for item in items]
        except PermissionError:
            raise unreadable(path, "primitive library index", SceneError) from None
        except (OSError, ValueError, KeyError, TypeError) as exc:  # JSON and Unicode errors are ValueErrors
            raise SceneError(
                f"{path}: not a primitive library index ({type(exc).__name__}: {exc}); "
                "write it with mi-lidar primitives extract"
            ) from None
        kind = (index.get("format", LIBRARY_FORMAT), index.get("version", LIBRARY_VERSION))
        if kind != (LIBRARY_FORMAT, LIBRARY_VERSION):
            raise SceneError(
                f"{path}: format {kind[0]!r} version {kind[1]!r}; this mi-lidar reads {LIBRARY_FORMAT!r} version "
                f"{LIBRARY_VERSION}: extract the library again with mi-lidar primitives extract"
            )
        return cls([_load_primitive(folder / file, id_, label, item) for id_, label, file, item in entries])

    def preview(self, path, per_class: int = 4, ids: list[str] | None = None) -> Path:
        """Save a PNG of side views (x-z) of primitives: 1-sigma ellipses coloured by p_hit, and boxes.

        Args:
            path: output ``.png``.
            per_class: primitives shown per class (ignored when ``ids`` is given).
            ids: primitive ids to show.
        """
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.patches import Ellipse, Rectangle

        if ids is not None:
            chosen = [p for p in self.primitives if p.id in set(ids)]
        else:
            chosen = []
            for c in sorted({p.label for p in self.primitives}):
                chosen += sorted(self.of_class(c), key=lambda p: -len(p.ellipsoids))[:per_class]
        if not chosen:
            raise SceneError("no primitives to preview")
        cols = min(per_class if ids is None else len(chosen), len(chosen))
        rows = int(np.ceil(len(chosen) / cols))
        fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 3.0 * rows), squeeze=False, layout="constrained")
        cmap = plt.get_cmap("viridis")
        for ax, p in zip(axes.ravel(), chosen):
            e = p.ellipsoids
            for mu, cov, ph in zip(e.means, e.covs, e.p_hit):
                w, v = np.linalg.eigh(cov[np.ix_([0, 2], [0, 2])])
                ang = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
                ax.add_patch(
                    Ellipse(
                        (mu[0], mu[2]),
                        2 * np.sqrt(w[1]),
                        2 * np.sqrt(w[0]),
                        angle=ang,
                        facecolor=cmap(ph),
                        alpha=0.5,
                        edgecolor="none",
                    )
                )
            ax.add_patch(Rectangle((p.box_lo[0], p.box_lo[2]), *(p.extents[[0, 2]]), fill=False, edgecolor="k", lw=0.8))
            ax.set_xlim(p.box_lo[0] - 0.5, p.box_hi[0] + 0.5)
            ax.set_ylim(p.box_lo[2] - 0.5, p.box_hi[2] + 0.5)
            ax.set_aspect("equal")
            ax.set_title(f"{p.class_name}\n{len(e)} ellipsoids", fontsize=8)
            ax.tick_params(labelsize=6)
        for ax in axes.ravel()[len(chosen) :]:
            ax.axis("off")
        fig.colorbar(plt.cm.ScalarMappable(cmap=cmap), ax=axes, label="p_hit", shrink=0.6)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=90)
        plt.close(fig)
        return Path(path)


def _load_primitive(path: Path, id_: str, label: int, item: dict) -> Primitive:
    """One primitive's ``.npz`` (see :meth:`PrimitiveLibrary.save`); SceneError naming the file when damaged."""
    if not path.is_file():
        raise SceneError(f"{path}: no such primitive file, yet library.json lists it; extract the library again")
    try:
        with np.load(path, allow_pickle=False) as d:
            arrays = {k: np.asarray(d[k], np.float64) for k in ("means", "covs", "p_hit", "box_lo", "box_hi")}
    except PermissionError:
        raise unreadable(path, "primitive", SceneError) from None
    except NPZ_MEMBER_ERRORS as exc:
        raise SceneError(
            f"{path}: not a primitive file ({numpy_file_problem(exc)}); extract the library again"
        ) from None
    n = len(arrays["means"])
    shapes = {"means": (n, 3), "covs": (n, 3, 3), "p_hit": (n,), "box_lo": (3,), "box_hi": (3,)}
    wrong = [f"{k} {arrays[k].shape} (expected {shape})" for k, shape in shapes.items() if arrays[k].shape != shape]
    if wrong or not all(np.isfinite(a).all() for a in arrays.values()):
        what = ", ".join(wrong) if wrong else "non-finite values"
        raise SceneError(f"{path}: damaged primitive: {what}; extract the library again")
    ellipsoids = EllipsoidSet(arrays["means"], arrays["covs"], arrays["p_hit"], label=label)
    source = item.get("source", {})
    return Primitive(
        id_, label, ellipsoids, arrays["box_lo"], arrays["box_hi"], source if isinstance(source, dict) else {}
    )
