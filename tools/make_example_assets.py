"""Generate the PLY assets of the bundled example scenes in ``scenes_xml/assets/``.

Run ``python tools/make_example_assets.py``; the output is deterministic (fixed seeds).
"""

from pathlib import Path

import numpy as np

from mi_lidar.scene.files import write_ellipsoids_ply, write_mesh_ply

ASSETS = Path(__file__).resolve().parents[1] / "scenes_xml" / "assets"
LABEL_GROUND, LABEL_SHRUB, LABEL_TREE = 1, 5, 6


def terrain_height(x, y):
    """Smooth rolling terrain height (m) at (x, y) (m)."""
    return 0.6 * np.sin(0.11 * x) * np.cos(0.07 * y) + 0.25 * np.sin(0.31 * x + 0.4) + 0.002 * x * y / 10


def terrain(size=60.0, step=1.0):
    """Grid mesh of the rolling terrain: (V, 3) vertices and (F, 3) faces."""
    ticks = np.arange(-size / 2, size / 2 + step / 2, step)
    gx, gy = np.meshgrid(ticks, ticks, indexing="ij")
    vertices = np.stack([gx, gy, terrain_height(gx, gy)], -1).reshape(-1, 3)
    n = len(ticks)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return vertices, faces


def vegetation(rng, n_shrubs=30, n_trees=10, size=50.0):
    """Shrubs (clusters of small ellipsoids) and tree canopies away from the sensor path."""
    centers, scales, labels, p_hit = [], [], [], []
    for kind, count in ((LABEL_SHRUB, n_shrubs), (LABEL_TREE, n_trees)):
        for _ in range(count):
            x, y = rng.uniform(-size / 2, size / 2, 2)
            if abs(y) < 3.0:  # keep the vehicle path (y = 0) free
                y += 6.0 * np.sign(y or 1.0)
            ground = terrain_height(x, y)
            blobs = rng.integers(4, 9)
            if kind == LABEL_SHRUB:
                offset = rng.normal(0, [0.5, 0.5, 0.2], (blobs, 3)) + [x, y, ground + 0.6]
                scale = rng.uniform(0.15, 0.35, (blobs, 3))
                prob = rng.uniform(0.3, 0.6, blobs)
            else:
                offset = rng.normal(0, [1.0, 1.0, 0.6], (blobs, 3)) + [x, y, ground + 4.0]
                scale = rng.uniform(0.4, 0.9, (blobs, 3))
                prob = rng.uniform(0.15, 0.35, blobs)
            centers.append(offset)
            scales.append(scale)
            p_hit.append(prob)
            labels.append(np.full(blobs, kind))
    centers, scales = np.concatenate(centers), np.concatenate(scales)
    angles = rng.uniform(0, np.pi, len(centers))
    quaternions = np.stack([np.zeros_like(angles), np.zeros_like(angles), np.sin(angles / 2), np.cos(angles / 2)], -1)
    return centers, scales, quaternions, np.concatenate(p_hit), np.concatenate(labels)


def street_trees():
    """Canopies of four street trees, 3 ellipsoids each."""
    centers, scales = [], []
    for x in (-12.0, -4.0, 4.0, 12.0):
        for dz, r in ((4.2, 1.4), (5.0, 1.1), (5.6, 0.8)):
            centers.append([x, 6.0, dz])
            scales.append([r / 2, r / 2, r / 2.5])
    n = len(centers)
    return np.array(centers), np.array(scales), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))


def main():
    rng = np.random.default_rng(7)
    vertices, faces = terrain()
    write_mesh_ply(ASSETS / "offroad_terrain.ply", vertices, faces, label=LABEL_GROUND)
    centers, scales, quats, p_hit, labels = vegetation(rng)
    write_ellipsoids_ply(ASSETS / "offroad_vegetation.ply", centers, scales, quats, p_hit=p_hit, label=labels)
    centers, scales, quats = street_trees()
    write_ellipsoids_ply(ASSETS / "street_trees.ply", centers, scales, quats, p_hit=0.25, label=LABEL_TREE)


if __name__ == "__main__":
    main()
