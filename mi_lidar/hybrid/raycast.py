"""Hybrid-model ray casting: element traversal, simulation, and hit / pass-through counting.

Along a ray the triangles and ellipsoids met are merged by entry range. Simulation draws a
Bernoulli(p_hit) at each element in order; the first success returns: a triangle gives its
nominal range plus N(0, range_sigma^2); an ellipsoid gives a range drawn from its Gaussian
restricted to the ray, N(t*, 1 / (d^T S^-1 d)) with t* = d^T S^-1 (mu - o) / (d^T S^-1 d).
This mirrors the core integrator's contract, so numbers measured here carry over to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import HybridModel
from .trace import ellipsoid_scene, mesh_scene, trace_elements


@dataclass
class Traversal:
    """Elements met by N rays, merged and sorted by entry range.

    Attributes:
        kind: (N, K) int8, 0 = triangle, 1 = ellipsoid, -1 = none.
        index: (N, K) element index within its kind (-1 = none).
        t: (N, K) entry range, m (inf = none).
    """

    kind: np.ndarray
    index: np.ndarray
    t: np.ndarray


class ModelTracer:
    """Mitsuba scenes of a :class:`HybridModel`, built once and reused for many ray batches."""

    def __init__(self, model: HybridModel):
        self.model = model
        g, e = model.ground, model.ellipsoids
        self.mesh = mesh_scene(g.vertices, g.faces) if len(g) else None
        if len(e):
            scales, quats = e.axes()
            self.ellipsoids = ellipsoid_scene(e.means, scales, quats, model.extent)
            self.inv_covs = np.linalg.inv(e.covs)
        else:
            self.ellipsoids = None

    def traverse(self, origins: np.ndarray, directions: np.ndarray, max_range, max_elements: int = 16) -> Traversal:
        """Merged element lists along rays ((N, 3) m, unit directions) up to ``max_range`` (m)."""
        n = len(origins)
        kinds, ids, ts = [], [], []
        for kind, scene in ((0, self.mesh), (1, self.ellipsoids)):
            if scene is None:
                continue
            i, t = trace_elements(scene, origins, directions, max_range, max_elements)
            kinds.append(np.where(i >= 0, kind, -1).astype(np.int8))
            ids.append(i)
            ts.append(t)
        if not ts:
            return Traversal(np.full((n, 0), -1, np.int8), np.full((n, 0), -1), np.full((n, 0), np.inf))
        kind, index, t = (np.concatenate(a, axis=1) for a in (kinds, ids, ts))
        order = np.argsort(t, axis=1, kind="stable")[:, :max_elements]
        take = lambda a: np.take_along_axis(a, order, axis=1)
        return Traversal(take(kind), take(index), take(t))

    def element_p_hit(self, trav: Traversal) -> np.ndarray:
        """(N, K) hit probability of each traversed element (0 where none)."""
        p = np.zeros(trav.t.shape)
        tri, ell = trav.kind == 0, trav.kind == 1
        p[tri] = self.model.ground.p_hit[trav.index[tri]]
        p[ell] = self.model.ellipsoids.p_hit[trav.index[ell]]
        return p

    def ray_mean(self, rows: np.ndarray, index: np.ndarray, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """Mean range t* and standard deviation (m) of ellipsoids ``index`` restricted to rays ``rows``."""
        e = self.model.ellipsoids
        prec = self.inv_covs[index]
        d = directions[rows]
        a = np.einsum("ni,nij,nj->n", d, prec, d)
        b = np.einsum("ni,nij,nj->n", d, prec, e.means[index] - origins[rows])
        return b / a, 1 / np.sqrt(a)


def simulate_rays(tracer: ModelTracer, origins: np.ndarray, directions: np.ndarray, rng: np.random.Generator,
                  max_range: float = 80.0, min_range: float = 1.0, max_elements: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Simulate one return per ray.

    Args:
        tracer: the model's scenes.
        origins, directions: (N, 3) world-frame rays, m.
        rng: random generator.
        max_range, min_range: sensor limits, m.
        max_elements: K, most elements considered per ray.

    Returns:
        ``ranges`` (N,) m (NaN = miss) and ``label`` (N,) int32 class of the returning element (0 = miss).
    """
    origins = np.asarray(origins, float)
    directions = np.asarray(directions, float)
    trav = tracer.traverse(origins, directions, max_range, max_elements)
    p = tracer.element_p_hit(trav)
    success = (rng.uniform(size=p.shape) < p) & (trav.kind >= 0)
    any_hit = success.any(axis=1)
    first = np.argmax(success, axis=1)
    rows = np.nonzero(any_hit)[0]
    kind = trav.kind[rows, first[rows]]
    index = trav.index[rows, first[rows]]
    r = np.full(len(origins), np.nan)
    label = np.zeros(len(origins), np.int32)
    tri = kind == 0
    g = tracer.model.ground
    r[rows[tri]] = trav.t[rows[tri], first[rows[tri]]] + rng.normal(0, 1, tri.sum()) * g.range_sigma[index[tri]]
    label[rows[tri]] = g.label[index[tri]]
    ell = ~tri
    if ell.any():
        mean, sd = tracer.ray_mean(rows[ell], index[ell], origins, directions)
        r[rows[ell]] = mean + sd * rng.normal(size=ell.sum())
        label[rows[ell]] = tracer.model.ellipsoids.label[index[ell]]
    bad = ~((r >= min_range) & (r <= max_range))
    r[bad] = np.nan
    label[bad] = 0
    return r, label


@dataclass
class HitCounts:
    """Hits and pass-throughs per element, and ground range residuals.

    Attributes:
        tri_hits, tri_pass: (F,) counts per triangle.
        ell_hits, ell_pass: (E,) counts per ellipsoid.
        residuals: (M,) measured minus nominal range of ground hits, m.
    """

    tri_hits: np.ndarray
    tri_pass: np.ndarray
    ell_hits: np.ndarray
    ell_pass: np.ndarray
    residuals: np.ndarray


def count_hits(tracer: ModelTracer, origins: np.ndarray, directions: np.ndarray, measured: np.ndarray,
               owner: np.ndarray, max_residual: float = 0.75, max_range: float = 80.0,
               max_elements: int = 16) -> HitCounts:
    """Count hits and pass-throughs of every element along logged rays (thesis p_hit counts).

    A triangle met at range t is *hit* if the measured return z satisfies ``|z - t| <=
    max_residual``, *passed* if the ray missed or ``z > t + max_residual``, and not counted if
    the ray stopped before it. An ellipsoid is hit by the rays whose return point belongs to its
    cluster (``owner``) and passed by every other ray that entered it before ``z - max_residual``
    (or missed).

    Args:
        tracer: the model's scenes.
        origins, directions: (N, 3) logged rays in the world frame.
        measured: (N,) measured ranges, m (NaN = miss).
        owner: (N,) ellipsoid index owning each return (-1 = none).
        max_residual: m ("maximum residual for hit").

    Returns:
        The :class:`HitCounts`.
    """
    model = tracer.model
    hit = np.isfinite(measured)
    z = np.where(hit, measured, np.inf)
    trav = tracer.traverse(origins, directions, np.where(hit, z + max_residual, max_range), max_elements)
    tri, ell = trav.kind == 0, trav.kind == 1
    resid = np.where(trav.kind >= 0, z[:, None] - np.where(trav.kind >= 0, trav.t, 0.0), -np.inf)
    tri_hit = tri & hit[:, None] & (np.abs(resid) <= max_residual)
    # at most one triangle hit per ray: the first one within tolerance
    first_tri = np.argmax(tri_hit, axis=1)
    one = np.zeros_like(tri_hit)
    rows = np.nonzero(tri_hit.any(axis=1))[0]
    one[rows, first_tri[rows]] = True
    tri_pass = tri & (resid > max_residual)
    ell_own = ell & (trav.index == owner[:, None])
    ell_pass = ell & ~ell_own & (resid > max_residual)
    nf, ne = len(model.ground), len(model.ellipsoids)
    count = lambda mask, n: np.bincount(trav.index[mask], minlength=n).astype(float)
    own = owner[owner >= 0]
    return HitCounts(count(one, nf), count(tri_pass, nf), np.bincount(own, minlength=ne).astype(float),
                     count(ell_pass, ne), resid[one])
