"""Ground segmentation by spherical variation (thesis eqs. 4.1-4.2) and the ground triangle mesh.

Segmentation: for each point the covariance of its neighbours within ``radius`` (the ``k``
nearest, at most) gives eigenvalues l1 <= l2 <= l3 and phi = l1 / (l1 + l2 + l3); fewer than
``min_neighbors`` neighbours give ``phi_default``. Optionally phi is smoothed with neighbours
within ``smooth_radius`` using the bilateral weights of eq. 4.2. Ground is ``phi < phi_thresh``.
Features are computed on a voxel-subsampled cloud and copied to every point of the voxel.

Surface: ground points are thinned to one point per ``grid`` cell (median height), isolated
points (no neighbour within ``isolated_dist``) are dropped, a compactly supported Wendland C2
RBF (support ``rbf_radius``, ridge ``regularization``) is fitted to the heights above a least
squares plane by conjugate gradients on the sparse system (O(N k)), the thinned points are
lifted onto the surface, Delaunay-triangulated in x-y, and triangles with a side longer than
``max_edge`` are removed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import cg
from scipy.spatial import Delaunay, cKDTree

from mi_lidar.hybrid.model import GroundMesh


@dataclass
class GroundParams:
    """Ground segmentation parameters (thesis table 4.1 names in brackets).

    Attributes:
        radius: neighbourhood radius d_phi, m ("maximum distance to neighbour").
        k: most neighbours used per point.
        min_neighbors: N_min,phi ("minimum neighbours to compute feature").
        phi_default: phi of points with too few neighbours.
        phi_thresh: ground if phi < phi_thresh.
        smooth_radius: d_smooth,phi of eq. 4.1, m; 0 disables smoothing.
        eta_d, eta_phi: weights of eq. 4.2.
        voxel: voxel size of the feature cloud, m.
    """

    radius: float = 1.0
    k: int = 24
    min_neighbors: int = 10
    phi_default: float = 0.01
    phi_thresh: float = 0.09
    smooth_radius: float = 0.0
    eta_d: float = 1.0
    eta_phi: float = 1.0
    voxel: float = 0.1


@dataclass
class SurfaceParams:
    """Ground surface and mesh parameters.

    Attributes:
        grid: thinning cell size, m.
        rbf_radius: support radius of the Wendland basis, m ("regression basis radius").
        regularization: ridge added to the RBF system ("regression regularization constant").
        isolated_dist: a thinned point with no neighbour closer than this is dropped, m.
        max_edge: triangles with a longer side are dropped, m ("maximum triangle side").
    """

    grid: float = 0.5
    rbf_radius: float = 2.5
    regularization: float = 1e-3
    isolated_dist: float = 2.0
    max_edge: float = 3.0


def voxel_index(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of one representative point per voxel and the voxel of every point.

    Args:
        points: (N, 3) m. voxel: cell size, m.

    Returns:
        ``first`` (M,) index of a representative per voxel and ``inverse`` (N,) voxel of each point.
    """
    keys = np.floor(points / voxel).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def spherical_variation(
    points: np.ndarray, radius: float, k: int, min_neighbors: int, default: float, workers: int = -1
) -> np.ndarray:
    """phi = l1 / (l1 + l2 + l3) of each point's neighbourhood (thesis 4.3.1.1).

    Args:
        points: (N, 3) m.
        radius: neighbourhood radius, m. k: most neighbours. min_neighbors: below this, ``default``.

    Returns:
        (N,) phi in [0, 1/3].
    """
    tree = cKDTree(points)
    dist, idx = tree.query(points, k=min(k, len(points)), distance_upper_bound=radius, workers=workers)
    valid = np.isfinite(dist)
    count = valid.sum(axis=1)
    nb = points[np.where(valid, idx, 0)]
    w = valid[..., None].astype(float)
    mean = (nb * w).sum(1) / np.maximum(count, 1)[:, None]
    centered = (nb - mean[:, None]) * w
    cov = np.einsum("nki,nkj->nij", centered, centered) / np.maximum(count - 1, 1)[:, None, None]
    lam = np.linalg.eigvalsh(cov)
    phi = lam[:, 0] / np.maximum(lam.sum(axis=1), 1e-12)
    return np.where(count >= min_neighbors, phi, default)


def smooth_variation(
    points: np.ndarray, phi: np.ndarray, radius: float, eta_d: float, eta_phi: float, k: int = 24, workers: int = -1
) -> np.ndarray:
    """Bilateral smoothing of phi over neighbours within ``radius`` (m), eqs. 4.1-4.2."""
    tree = cKDTree(points)
    dist, idx = tree.query(points, k=min(k, len(points)), distance_upper_bound=radius, workers=workers)
    valid = np.isfinite(dist)
    nphi = phi[np.where(valid, idx, 0)]
    w = np.exp(-eta_d * np.where(valid, dist, 0) ** 2 / radius**2 - eta_phi * (phi[:, None] - nphi) ** 2 / (1 / 3) ** 2)
    w = np.where(valid, w, 0)
    return (w * nphi).sum(1) / np.maximum(w.sum(1), 1e-12)


def ground_features(points: np.ndarray, params: GroundParams) -> np.ndarray:
    """(N,) phi of every point (computed per voxel of size ``params.voxel`` and smoothed if asked)."""
    first, inverse = voxel_index(points, params.voxel)
    rep = points[first]
    phi = spherical_variation(rep, params.radius, params.k, params.min_neighbors, params.phi_default)
    if params.smooth_radius > 0:
        phi = smooth_variation(rep, phi, params.smooth_radius, params.eta_d, params.eta_phi, params.k)
    return phi[inverse]


def segment_ground(points: np.ndarray, params: GroundParams, phi: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: True for ground points (``phi < phi_thresh``)."""
    phi = ground_features(points, params) if phi is None else phi
    return phi < params.phi_thresh


def tune_threshold(phi: np.ndarray, is_ground: np.ndarray, candidates: np.ndarray | None = None) -> tuple[float, float]:
    """Threshold on phi maximizing accuracy against labels.

    Args:
        phi: (N,) features. is_ground: (N,) bool truth. candidates: thresholds to try.

    Returns:
        (best threshold, its accuracy).
    """
    candidates = np.linspace(0.005, 0.2, 40) if candidates is None else candidates
    acc = np.array([np.mean((phi < c) == is_ground) for c in candidates])
    best = int(np.argmax(acc))
    return float(candidates[best]), float(acc[best])


# --------------------------------------------------------------------------- surface and mesh
class WendlandSurface:
    """z(x, y) = plane + sum_j w_j phi(|p - c_j| / R), phi(r) = (1 - r)^4 (4 r + 1) for r < 1.

    Args:
        centers: (M, 2) RBF centres, m. heights: (M,) heights at the centres, m.
        radius: support R, m. regularization: ridge lambda added to the kernel diagonal.
    """

    def __init__(self, centers: np.ndarray, heights: np.ndarray, radius: float, regularization: float):
        self.centers = np.asarray(centers, float)
        self.radius = float(radius)
        self.tree = cKDTree(self.centers)
        design = np.c_[self.centers, np.ones(len(self.centers))]
        self.plane = np.linalg.lstsq(design, heights, rcond=None)[0]
        system = self._kernel(self.centers) + regularization * sparse.identity(len(self.centers), format="csr")
        self.weights, _ = cg(system, heights - design @ self.plane, rtol=1e-6, maxiter=2000)

    def _kernel(self, points: np.ndarray) -> sparse.csr_matrix:
        pairs = cKDTree(points).sparse_distance_matrix(self.tree, self.radius, output_type="ndarray")
        r = pairs["v"] / self.radius
        values = (1 - r) ** 4 * (4 * r + 1)
        return sparse.csr_matrix((values, (pairs["i"], pairs["j"])), shape=(len(points), len(self.centers)))

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Heights (N,) at (N, 2) positions, m."""
        xy = np.asarray(xy, float)
        return np.c_[xy, np.ones(len(xy))] @ self.plane + self._kernel(xy) @ self.weights


def thin_grid(points: np.ndarray, grid: float) -> np.ndarray:
    """(M, 3) one point per ``grid`` (m) x-y cell: the cell's mean x-y and median height."""
    keys = np.floor(points[:, :2] / grid).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    xy = np.stack([np.bincount(inverse, points[:, i]) / counts for i in (0, 1)], 1)
    order = np.lexsort((points[:, 2], inverse))
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    z = points[order[starts + counts // 2], 2]
    return np.c_[xy, z]


def fit_ground_mesh(points: np.ndarray, params: SurfaceParams, keep_xy: tuple | None = None) -> GroundMesh:
    """Triangle mesh through ground points.

    Args:
        points: (N, 3) ground points, m.
        params: surface parameters.
        keep_xy: optional (xmin, ymin, xmax, ymax) m; only triangles whose centroid lies inside are kept
            (blocks fit with a margin and keep their own triangles).

    Returns:
        The mesh (element attributes left at defaults).
    """
    if len(points) < 3:
        return GroundMesh(np.zeros((0, 3)), np.zeros((0, 3)))
    thin = thin_grid(points, params.grid)
    if len(thin) > 1:
        nn, _ = cKDTree(thin).query(thin, k=2)
        thin = thin[nn[:, 1] <= params.isolated_dist]
    if len(thin) < 3:
        return GroundMesh(np.zeros((0, 3)), np.zeros((0, 3)))
    surface = WendlandSurface(thin[:, :2], thin[:, 2], params.rbf_radius, params.regularization)
    vertices = np.c_[thin[:, :2], surface(thin[:, :2])]
    faces = Delaunay(thin[:, :2]).simplices
    tri = vertices[faces]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    keep = edges <= params.max_edge
    if keep_xy is not None:
        c = tri[:, :, :2].mean(axis=1)
        keep &= (c[:, 0] >= keep_xy[0]) & (c[:, 1] >= keep_xy[1]) & (c[:, 0] < keep_xy[2]) & (c[:, 1] < keep_xy[3])
    return GroundMesh(vertices, faces[keep])
