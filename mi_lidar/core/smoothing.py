"""Smoothed ellipsoid elements: the fitting-only surrogate that makes their geometry recoverable.

The exact likelihood of an ellipsoid element is discontinuous in its centre and scales: a ray
meets the element only inside its silhouette (closest Mahalanobis approach ``m < E``, ``E`` the
extent) and a return is possible only inside the chord. A return that the current geometry puts
outside the chord or silhouette scores the robustness floor (about 20 nats) and has no gradient,
while the returns inside pull the chord *shorter* (a truncated density is higher on a shorter
chord). Measured on 24 shrubs perturbed by 3-5 cm and +-20 %, every such floored return was
behind the whole gap to the truth's loss, and Adam walked away from the truth.

While fitting ellipsoid centres or scales, the training loss therefore uses a smoothed element,
with a smoothing ``kappa`` in sigmas of the element (annealed towards 0, where the surrogate is
the exact model; :func:`smoothing_at`):

* **soft chord ends**: the restricted Gaussian ``N(mu, s^2)`` is multiplied by the chord's
  indicator blurred by ``N(0, tau^2)``, ``tau = kappa s`` (:func:`smoothed_log_density`, normalized in
  closed form), so a return beyond a chord end is a Gaussian tail, not the floor, while the
  density inside stays exact (blurring the whole density instead widens it, and the fit then
  shrinks every chord);
* **soft silhouette**: the element returns with ``p Phi((E - m) / kappa)`` instead of
  ``p 1[m < E]`` (:func:`presence`), so a ray just outside it still pulls it closer;
* **margin**: rays are traced against ellipsoids inflated to ``E + REACH kappa`` sigmas
  (:func:`inflation`), so the rays of that soft rim get a segment.

The held-out loss (early stopping, reports) is always the exact likelihood on an exact trace.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.segment import ELLIPSOID, LOG_SQRT_2PI, Segment, log_density, normal_cdf

REACH = 3.0  # traced margin of the soft silhouette, in smoothings (Phi(-3) = 0.1 % presence)
NARROW = 1e-3  # intervals narrower than this (standard units) use the midpoint rule


def smoothing_at(step: int, steps: int, start: float, final: float) -> float:
    """Smoothing (sigmas) of Adam step ``step`` of ``steps``: geometric from ``start`` to ``final``."""
    if start <= 0:
        return 0.0
    return start * (final / start) ** (min(step, steps) / max(steps, 1))


def presence(closest_sq: mi.Float, extent: mi.Float, kappa: float) -> mi.Float:
    """Soft indicator ``Phi((E - m) / kappa)`` that the ray meets the element.

    Args:
        closest_sq: ``m^2``, the squared Mahalanobis distance of the ray's closest approach to the element's
            centre, sigmas squared (:func:`mi_lidar.core.segment.ray_closest_approach`).
        extent: the element's extent ``E``, sigmas.
        kappa: smoothing, sigmas (> 0).
    """
    closest = dr.sqrt(dr.maximum(closest_sq, 1e-12))
    return normal_cdf((extent - closest) / dr.opaque(mi.Float, kappa))


def _log_mean_phi(lo: mi.Float, hi: mi.Float) -> mi.Float:
    """``log((Phi(hi) - Phi(lo)) / (hi - lo))``: log of the mean standard normal density on ``[lo, hi]``.

    Finite (and with finite gradients) as the interval shrinks to a point; tails are taken on the
    side nearer zero so that float32 keeps precision.
    """
    width = hi - lo
    middle = 0.5 * (lo + hi)
    mass = dr.select(middle > 0, normal_cdf(-lo) - normal_cdf(-hi), normal_cdf(hi) - normal_cdf(lo))
    wide = dr.log(dr.maximum(mass, 1e-30)) - dr.log(dr.maximum(width, NARROW))
    narrow = -0.5 * middle * middle - LOG_SQRT_2PI
    return dr.select(width > NARROW, wide, narrow)


def smoothed_log_density(seg: Segment, z: mi.Float, kappa: float) -> mi.Float:
    """Log density (1/m) of ``z`` under each lane's return distribution with soft chord ends.

    Ellipsoid lanes: the Gaussian ``N(mean, sigma^2)`` times the chord's indicator convolved with
    ``N(0, tau^2)``, ``tau = kappa sigma``, normalized in closed form (``S^2 = sigma^2 + tau^2``):
    ``N(z; mean, sigma^2) (Phi((hi - z) / tau) - Phi((lo - z) / tau)) / (Phi((hi - mean) / S) - Phi((lo - mean) / S))``.
    Inside the chord, away from its ends, it is the exact density (the spread is not widened); it
    tends to :func:`~mi_lidar.core.segment.log_density` as ``kappa -> 0`` and stays finite, a Gaussian of
    width about ``tau`` at ``mean``, as the chord shrinks to a point. Other lanes:
    :func:`~mi_lidar.core.segment.log_density`.
    """
    sigma = dr.maximum(seg.sigma, 1e-9)
    tau = dr.opaque(mi.Float, kappa) * sigma  # a kernel input: annealing does not recompile
    spread = dr.sqrt(sigma * sigma + tau * tau)
    gaussian = -0.5 * dr.square((z - seg.mean) / sigma) - dr.log(sigma) - LOG_SQRT_2PI
    window = _log_mean_phi((seg.lo - z) / tau, (seg.hi - z) / tau)
    mass = _log_mean_phi((seg.lo - seg.mean) / spread, (seg.hi - seg.mean) / spread)
    # the chord is (hi - lo) / tau wide in the window and (hi - lo) / S in the mass: their ratio
    value = gaussian + window - mass + dr.log(spread / tau)
    return dr.select(seg.kind == ELLIPSOID, value, log_density(seg, z))


def inflation(scales: np.ndarray, kappa: float, extent: np.ndarray) -> np.ndarray:
    """(N, 3) scales (m) inflated so that the extent-``E`` surface lies at ``E + REACH kappa`` sigmas."""
    return scales * (1.0 + REACH * kappa / np.asarray(extent, np.float64))[:, None]
