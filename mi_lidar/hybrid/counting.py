"""Hits and pass-throughs of every element along logged rays (the data behind p_hit).

Thesis 4.3.1.2: ``p_hit = #hits / (#hits + #misses)``, where a miss counts a ray that passed
through the element. Rays are traversed in the model's Mitsuba scene with the core's rules
(:func:`.simulation.trace_elements`); ``z`` is the logged range, ``t`` the entry range of an
element and ``r = z - t``.

* **Triangles.** The first triangle with ``|r| <= max_residual`` is hit, unless the return
  belongs to an ellipsoid cluster. A triangle is passed only when the return lies beyond it by
  more than ``max_residual`` along the ray *and* by more than ``pass_sigmas`` standard
  deviations of the ground's height residual along its normal (``r cos(incidence) >
  pass_sigmas * sigma_n``), or the ray missed. The second condition is the grazing fix: a beam
  that grazes a smoothed surface fitted slightly above the true ground crosses it metres before
  the real return, although only centimetres separate the return from the surface; such rays
  are neither hits nor pass-throughs. ``sigma_n`` is the RMS of ``r cos(incidence)`` over
  triangle hits.
* **Ellipsoids.** Hit by the rays whose return point belongs to the cluster (``owner``);
  passed by every other ray that entered it more than ``max_residual`` before its return (or
  missed).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mi_lidar.core.elements import ElementTable
from mi_lidar.hybrid.simulation import ELLIPSOIDS_ID, GROUND_ID, trace_elements


@dataclass
class HitCounts:
    """Hits and pass-throughs per element, and ground residuals.

    Attributes:
        tri_hits, tri_pass: (F,) counts per triangle.
        ell_hits, ell_pass: (E,) counts per ellipsoid.
        residuals: (M,) range residuals ``z - t`` of triangle hits, m.
        sigma_normal: RMS residual of triangle hits along the triangle normal, m.
        grazing: crossings neither hit nor passed because of the normal test.
    """

    tri_hits: np.ndarray
    tri_pass: np.ndarray
    ell_hits: np.ndarray
    ell_pass: np.ndarray
    residuals: np.ndarray
    sigma_normal: float
    grazing: int


def count_hits(
    scene,
    origins: np.ndarray,
    directions: np.ndarray,
    measured: np.ndarray,
    owner: np.ndarray,
    n_triangles: int,
    n_ellipsoids: int,
    max_residual: float = 0.75,
    pass_sigmas: float = 3.0,
    max_range: float = 80.0,
    max_elements: int = 16,
    chunk: int = 400_000,
    progress: Callable[[float], None] | None = None,
) -> HitCounts:
    """Count hits and pass-throughs along logged rays (see the module docstring).

    Args:
        scene: the model's scene (:func:`.simulation.load_model`).
        origins, directions: (N, 3) logged world rays, m.
        measured: (N,) logged ranges, m (NaN = miss).
        owner: (N,) ellipsoid owning each return (-1 = none).
        n_triangles, n_ellipsoids: element counts of the model.
        max_residual: m, along the ray ("maximum residual for hit", table 4.1).
        pass_sigmas: k of the normal-distance test for triangle pass-throughs.
        max_range: sensor range for rays that missed, m.
        max_elements: elements traced per ray. chunk: rays traced at once.
        progress: optional callback receiving the fraction of rays done.

    Returns:
        The :class:`HitCounts`.
    """
    table = ElementTable.from_scene(scene)
    tri_hits, ell_hits, ell_pass = np.zeros(n_triangles), np.zeros(n_ellipsoids), np.zeros(n_ellipsoids)
    residuals, normal_resid, pass_tri, pass_depth = [], [], [], []
    for start in range(0, len(origins), chunk):
        sl = slice(start, start + chunk)
        z = measured[sl]
        hit = np.isfinite(z)
        z = np.where(hit, z, np.inf)
        trav = trace_elements(
            scene, table, origins[sl], directions[sl], np.where(hit, z + max_residual, max_range), max_elements
        )
        tri, ell = trav.of(GROUND_ID), trav.of(ELLIPSOIDS_ID)
        resid = np.where(trav.shape >= 0, z[:, None] - np.where(trav.shape >= 0, trav.t, 0.0), -np.inf)
        own = owner[sl]
        near = tri & (hit & (own < 0))[:, None] & (np.abs(resid) <= max_residual)
        rows = np.flatnonzero(near.any(axis=1))
        first = np.argmax(near[rows], axis=1)
        tri_hits += np.bincount(trav.index[rows, first], minlength=n_triangles)
        residuals.append(resid[rows, first])
        normal_resid.append(resid[rows, first] * trav.cos[rows, first])
        beyond = tri & (resid > max_residual)
        pass_tri.append(trav.index[beyond])
        pass_depth.append(np.where(np.isfinite(resid), resid, np.inf)[beyond] * trav.cos[beyond])
        owned = ell & (trav.index == own[:, None])
        ell_hits += np.bincount(own[own >= 0], minlength=n_ellipsoids)
        ell_pass += np.bincount(trav.index[ell & ~owned & (resid > max_residual)], minlength=n_ellipsoids)
        if progress is not None:
            progress(min(start + chunk, len(origins)) / max(len(origins), 1))
    normal_resid = np.concatenate(normal_resid)
    sigma_n = float(np.sqrt(np.mean(normal_resid**2))) if len(normal_resid) else 0.0
    depth = np.concatenate(pass_depth)
    passed = depth > pass_sigmas * sigma_n
    tri_pass = np.bincount(np.concatenate(pass_tri)[passed], minlength=n_triangles).astype(float)
    return HitCounts(tri_hits, tri_pass, ell_hits, ell_pass, np.concatenate(residuals), sigma_n, int((~passed).sum()))
