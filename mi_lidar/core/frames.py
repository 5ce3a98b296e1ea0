"""Local frames: georeferenced coordinates in float32, and the local origin that keeps them exact.

Mitsuba stores geometry and rays in float32, whose step grows with the magnitude: 0.03 m at a UTM
easting of 500,000 m, 0.25 m at a northing of 4,000,000 m. A scan simulated there is wrong by
decimetres. Every path that takes world coordinates (scene XML, point clouds, poses, the hybrid
fit) therefore works in a *local frame*: world coordinates minus an ``origin`` (float64, m) chosen
once per scene with :func:`local_origin`, applied to geometry and poses alike and added back to
what is written in world coordinates. Coordinates that cannot be moved (a mesh file's own
vertices) are checked with :func:`check_float32`, which names the value and the fix.

Loaded scenes carry their origin themselves (:func:`set_scene_origin`, :func:`scene_origin`): Mitsuba's
scene objects take neither attributes nor weak references, but they have an ``id`` string, which
gets a mark ``mi_lidar.origin=x,y,z`` (a table keyed by the object's address would hand a freed
scene's origin to the next scene allocated there).
"""

from __future__ import annotations

import numpy as np

from mi_lidar.core.errors import MiLidarError

MAX_COORDINATE_M = 1e8  # beyond any Lidar's range and any Earth-fixed coordinate: a larger one is a misread number
NEAR_M = 1024.0  # coordinates up to this magnitude keep 0.12 mm in float32: no local origin needed
RESOLUTION_M = 1e-3  # coarsest float32 step (m) accepted on coordinates that reach Mitsuba
COORDINATES_DOC = "docs/coordinates.md"

ORIGIN_MARK = "mi_lidar.origin="  # in a scene's id: the world position of its local frame


def float32_step(magnitude: float) -> float:
    """Spacing (m) of float32 numbers at ``magnitude`` (m): 0.25 at 4e6, 0.03125 at 5e5, 1.2e-4 at 1024."""
    return float(np.spacing(np.float32(abs(magnitude))))


def max_magnitude(points) -> float:
    """Largest finite ``|coordinate|`` (m) of ``points`` (any shape; 0 when none is finite)."""
    values = np.abs(np.asarray(points, dtype=np.float64))
    values = values[np.isfinite(values)]
    return float(values.max()) if values.size else 0.0


def local_origin(points) -> np.ndarray:
    """The local origin (m, float64 (3,)) of world coordinates ``points`` (N, 3).

    Zero when every finite coordinate lies within :data:`NEAR_M` of the world origin (the frame is
    already local, so results stay bit-identical); otherwise the centre of the points' bounding box
    rounded to whole metres, so that local coordinates are the smallest they can be and the origin
    reads well in a file (``translate x="500012" y="4000031" z="104"``).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    if not len(points) or max_magnitude(points) <= NEAR_M:
        return np.zeros(3)
    return np.round((points.min(axis=0) + points.max(axis=0)) / 2) + 0.0  # + 0.0: no negative zeros


def shift_poses(poses: np.ndarray, offset) -> np.ndarray:
    """``poses`` (S, 4, 4) with ``offset`` (3,) m subtracted from their positions (float64 copy).

    ``shift_poses(world, origin)`` gives poses in the local frame; ``shift_poses(local, -origin)``
    gives them back in the world frame.
    """
    shifted = np.array(poses, dtype=np.float64)
    shifted[..., :3, 3] -= np.asarray(offset, dtype=np.float64)
    return shifted


def needs_float64(points) -> bool:
    """Whether float32 keeps coordinates ``points`` (m, any shape) more coarsely than :data:`RESOLUTION_M`."""
    return float32_step(max_magnitude(points)) > RESOLUTION_M


def check_float32(points, source: str, what: str, fix: str, error: type[MiLidarError]) -> None:
    """Refuse coordinates that float32 keeps more coarsely than :data:`RESOLUTION_M`.

    Args:
        points: coordinates (m), any shape.
        source: the file or object, first in the message.
        what: what the coordinates are, e.g. ``"vertex coordinates"``.
        fix: what to do, one sentence.
        error: the exception type.

    Raises:
        error: e.g. ``scene.xml: vertex coordinates reach 4,000,123 m; float32 keeps 0.25 m there. <fix>``.
    """
    if needs_float64(points):
        raise error(float32_message(points, source, what, fix))


def float32_message(points, source: str, what: str, fix: str) -> str:
    """``<source>: <what> reach 4,000,123 m; float32 keeps 0.25 m there. <fix>`` for coordinates ``points`` (m)."""
    largest = max_magnitude(points)
    return f"{source}: {what} reach {largest:,.0f} m; float32 keeps {float32_step(largest):.3g} m there. {fix}"


def set_scene_origin(scene, origin) -> None:
    """Record in ``scene`` that its geometry is in a local frame whose origin is ``origin`` (3,) m in the world."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    own = scene.id().split(ORIGIN_MARK)[0].rstrip()
    mark = f"{ORIGIN_MARK}{','.join(repr(float(v)) for v in origin)}" if np.any(origin) else ""
    scene.set_id(" ".join(part for part in (own, mark) if part))


def scene_origin(scene) -> np.ndarray:
    """The world position (m, float64 (3,)) of ``scene``'s local frame: zero for a scene in world coordinates."""
    _, found, values = scene.id().partition(ORIGIN_MARK)
    return np.array([float(v) for v in values.split(",")]) if found else np.zeros(3)
