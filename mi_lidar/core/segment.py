"""One element met by a ray: what happens to the beam there, and the distribution of the range it returns.

Every element a ray meets becomes a :class:`Segment`, a struct of Dr.Jit arrays (one lane per
ray). The beam reaching it is *intercepted* with probability ``p`` (a permeable element lets it pass
otherwise, to the next element); an intercepted beam is *lost* (no return, nothing behind revealed:
a dark, specular or too distant surface) with probability ``drop``, and otherwise returns. Along a
ray the elements ``k = 1..K`` are met in order, so with ``pi_k = prod_{j<k} (1 - p_j)`` the beam
returns from element ``k`` with probability ``pi_k p_k (1 - drop_k)``, is lost there with
``pi_k p_k drop_k`` and passes them all with ``pi_{K+1}``.

The return distribution is given by the sensor model's return density
(:mod:`mi_lidar.core.densities`); the default, the element Gaussian, is ``N(mean, sigma^2)``
truncated to ``[lo, hi]``:

* a triangle returns its nominal range plus noise: ``mean = r``, ``sigma = range_sigma``,
  ``[lo, hi] = (-inf, inf)``;
* an ellipsoid returns a range drawn from its 3D Gaussian ``N(mu, Sigma)`` *restricted to the
  ray* (the conditional density along the beam, which keeps the point on the beam), truncated to
  the chord the ray cuts through the ellipsoid's ``extent``. Along ``o + t d`` the Mahalanobis
  distance is the quadratic ``a t^2 + 2 b t + c``, so the restricted Gaussian has
  ``mean = -b / a``, ``sigma = 1 / sqrt(a)`` and the chord is ``mean +- sqrt((E^2 - m^2) / a)``
  with ``m^2 = c - b^2 / a`` the closest approach and ``E`` the extent.

A triangle also knows its *corners* along the ray: the range at which the ray passes each vertex
(``corner_offset``, relative to the plane's range) and the barycentric weights of the point it hits
(``corner_weight``). A mesh made of samples of a surface (a range-image mesh, a fitted ground)
interpolates linearly between them; at a depth edge the sensor instead sees the surface of one of the
samples, the foreground or the background. With ``corner_share`` ``s > 0`` (the ``corner_returns``
effect) a surface returns from the plane with probability ``1 - s`` and from corner ``i`` with
probability ``s w_i``, each with the element's Gaussian: the density is the mixture
``(1 - s) N(z; mean, sigma^2) + s sum_i w_i N(z; mean + offset_i, sigma^2)``.

Effects (``mi_lidar.core.effects``) edit ``p``, ``drop``, ``mean``, ``sigma`` and ``corner_share``;
sampling and the likelihood read the edited values through the same density, so the two stay
consistent by construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

SURFACE = 0
ELLIPSOID = 1
INV_SQRT2 = 1.0 / math.sqrt(2.0)
LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
DEFAULT_REFLECTIVITY = 0.5  # Lambertian reflectivity of elements that set none (lidar_material's default)
# Largest |cos(incidence)| a law differentiates through: acos and sqrt(1 - cos^2) have an infinite slope at 1, where
# float32 rounds the cos of a ray within 2.4e-4 rad of a surface's normal; times the ~0 slope of the cos in a ray's
# angle that made NaN gradients for effects that move rays.
MAX_COS = 0.9999999


@dataclass
class Segment:
    """Element ``k`` met along each ray (all fields have one lane per ray).

    Attributes:
        valid: the ray met an element in this round.
        nominal: nominal range: distance from the ray origin to the entry point (m).
        p: probability that the element intercepts the beam (pass-through otherwise).
        mean, sigma: location and Gaussian scale of the returned range (m).
        lo, hi: truncation bounds of that Gaussian (m; +-inf for surfaces).
        cos_incidence: |cos| of the angle between the beam and the surface normal.
        element: global element index (see :class:`mi_lidar.core.elements.ElementTable`).
        shape: shape index in the element table.
        label: class label of the element.
        kind: ``SURFACE`` or ``ELLIPSOID``.
        drop: probability that an intercepted beam gives no return (the beam stops); 0 by default.
        reflectivity: Lambertian reflectivity of the element at the sensor's wavelength (1 = white
            diffuse target); sets the returned power (intensity, weak-return dropout).
        corner_offset: range (m) at which the ray passes each vertex of a triangle, minus the plane's
            range (zeros for other elements); None where the tracer knows no corners.
        corner_weight: barycentric weights of the hit point on a triangle (``(1, 0, 0)`` for other
            elements).
        corner_share: probability ``s`` that the return comes from a corner's surface (0: the plane).
        corner_sigma: Gaussian scale (m) of a corner's return (None: ``sigma``, the plane's).
    """

    valid: mi.Bool
    nominal: mi.Float
    p: mi.Float
    mean: mi.Float
    sigma: mi.Float
    lo: mi.Float
    hi: mi.Float
    cos_incidence: mi.Float
    element: mi.UInt32
    shape: mi.UInt32
    label: mi.UInt32
    kind: mi.UInt32
    drop: mi.Float | float = 0.0
    reflectivity: mi.Float | float = DEFAULT_REFLECTIVITY
    corner_offset: mi.Vector3f | None = None
    corner_weight: mi.Vector3f | None = None
    corner_share: mi.Float | float = 0.0
    corner_sigma: mi.Float | None = None

    def with_(self, **changes) -> Segment:
        """A copy with some fields replaced (effects use this)."""
        return replace(self, **changes)


def incidence_deg(cos_incidence: mi.Float) -> mi.Float:
    """Incidence angle (deg) of each lane's ``|cos|``, differentiable away from the normal.

    The value is ``acos(clip(cos, 0, 1))`` in every lane. Within 4.9e-4 rad of the normal (``cos`` above
    :data:`MAX_COS`) it carries no gradient: acos's slope in ``cos`` is infinite at 1, and the lanes of rays on a
    surface's normal (``cos`` = 1 in float32) sent -inf, times the zero slope of the cos in the ray's angle NaN,
    into the angle offsets of a fit.

    Args:
        cos_incidence: (N,) ``|cos|`` of the incidence angle (NaN where unknown: the angle is NaN too).

    Returns:
        (N,) incidence angle, deg, in [0, 90].
    """
    cos = dr.clip(cos_incidence, 0.0, 1.0)
    angle = dr.select(cos <= MAX_COS, dr.acos(dr.minimum(cos, MAX_COS)), dr.detach(dr.acos(cos)))
    return angle * (180.0 / math.pi)


def normal_cdf(x: mi.Float) -> mi.Float:
    """Standard normal CDF."""
    return 0.5 * (1.0 + dr.erf(x * INV_SQRT2))


def normal_mass(mean: mi.Float, sigma: mi.Float, a, b) -> mi.Float:
    """Mass of each lane's Gaussian ``N(mean, sigma^2)`` (m) on ``[a, b]`` (m; floats or per-lane arrays)."""
    return normal_cdf((b - mean) / sigma) - normal_cdf((a - mean) / sigma)


def is_open(a: float, b: float) -> bool:
    """True when the range window ``[a, b]`` (m) cuts nothing a sensor reports: ``a <= 0`` and ``b`` infinite."""
    return a <= 0.0 and b == math.inf


def has_corners(seg: Segment) -> bool:
    """True when ``seg`` may return from its corners (known corners and a share that is not a literal 0)."""
    share = seg.corner_share
    return seg.corner_offset is not None and not (isinstance(share, (int, float)) and share == 0)


def _components(seg: Segment) -> list[tuple]:
    """The corner mixture of a segment with corners: ``(weight, mean, sigma)`` of the plane, then of each corner."""
    offset, weight = seg.corner_offset, seg.corner_weight
    if offset is None or weight is None:
        raise ValueError("a segment without corners has no corner mixture")
    share = seg.corner_share
    corner_sigma = seg.sigma if seg.corner_sigma is None else seg.corner_sigma
    return [(1.0 - share, seg.mean, seg.sigma)] + [
        (share * weight[i], seg.mean + offset[i], corner_sigma) for i in range(3)
    ]


def _corner_choice(seg: Segment, u: mi.Float) -> tuple[mi.Float, mi.Float, mi.Float]:
    """The component of the corner mixture ``u`` picks: its mean (m), sigma (m) and ``u`` rescaled to [0, 1)."""
    components = _components(seg)
    _, mean, sigma = components[0]
    start, width, edge = dr.zeros(mi.Float, dr.width(u)), components[0][0], components[0][0]
    for w, m, sd in components[1:]:
        pick = (u >= edge) & (u < edge + w)
        start, width = dr.select(pick, edge, start), dr.select(pick, w, width)
        mean, sigma = dr.select(pick, m, mean), dr.select(pick, sd, sigma)
        edge = edge + w
    return mean, sigma, dr.clip((u - start) / dr.maximum(width, 1e-12), 0.0, 1.0 - 1e-7)


def sample_range(seg: Segment, u: mi.Float) -> mi.Float:
    """Draw the returned range of each lane from its truncated Gaussian by inversion.

    With corner returns (:func:`has_corners`) ``u`` first picks the plane or a corner, then is
    rescaled to draw the range from that component's Gaussian.

    Args:
        seg: the segment (``mean``, ``sigma``, ``lo``, ``hi``; corners).
        u: uniform samples in [0, 1), one per lane.

    Returns:
        Ranges in m; where the truncated mass is negligible (< 1e-6, a grazing chord far from the
        mean) the range is uniform on ``[lo, hi]``.
    """
    if has_corners(seg):
        mean, sigma, u = _corner_choice(seg, u)
        seg = seg.with_(mean=mean, sigma=sigma)
    sigma = dr.maximum(seg.sigma, 1e-9)
    cdf_lo = normal_cdf((seg.lo - seg.mean) / sigma)
    cdf_hi = normal_cdf((seg.hi - seg.mean) / sigma)
    mass = cdf_hi - cdf_lo
    v = dr.clip(cdf_lo + u * mass, 1e-7, 1.0 - 1e-7)
    z = seg.mean + sigma * math.sqrt(2.0) * dr.erfinv(2.0 * v - 1.0)
    z = dr.clip(z, seg.lo, seg.hi)
    return dr.select(mass > 1e-6, z, seg.lo + u * (seg.hi - seg.lo))


def log_density(seg: Segment, z: mi.Float) -> mi.Float:
    """Log density (1/m) of range ``z`` under each lane's truncated Gaussian (-inf outside), or its
    corner mixture (:func:`has_corners`)."""
    if not has_corners(seg):
        return _gaussian_log_density(seg, z)
    terms = [(w, _gaussian_log_density(seg.with_(mean=m, sigma=sd), z)) for w, m, sd in _components(seg)]
    top = terms[0][1]
    for _, value in terms[1:]:
        top = dr.maximum(top, value)
    safe = dr.select(dr.isinf(top), 0.0, top)
    total = sum((w * dr.exp(value - safe) for w, value in terms[1:]), terms[0][0] * dr.exp(terms[0][1] - safe))
    return dr.select(dr.isinf(top), top, safe + dr.log(dr.maximum(total, 1e-30)))


def window_probability(seg: Segment, a: float, b: float) -> mi.Float:
    """Probability that a return from each lane's law reports a range in ``[a, b]`` (m): the truncated
    Gaussian's mass there (the uniform's overlap where its truncated mass is negligible), or its corner
    mixture's. The sensor reports nothing outside its range window (see :meth:`SensorModel.censor`)."""
    if not has_corners(seg):
        return _gaussian_window(seg, a, b)
    return sum(w * _gaussian_window(seg.with_(mean=m, sigma=sd), a, b) for w, m, sd in _components(seg))


def _gaussian_window(seg: Segment, a: float, b: float) -> mi.Float:
    """Mass of each lane's truncated Gaussian on ``[a, b]`` (m), in [0, 1]."""
    sigma = dr.maximum(seg.sigma, 1e-9)
    low, high = dr.maximum(seg.lo, a), dr.minimum(seg.hi, b)
    mass = normal_mass(seg.mean, sigma, seg.lo, seg.hi)
    part = normal_mass(seg.mean, sigma, low, high)
    gaussian = part / dr.maximum(mass, 1e-30)
    span = seg.hi - seg.lo
    uniform = dr.select(span > 1e-9, (high - low) / dr.maximum(span, 1e-9), 1.0)
    value = dr.select(mass > 1e-6, gaussian, uniform)
    return dr.select(high >= low, dr.clip(value, 0.0, 1.0), 0.0)


def range_moments(seg: Segment) -> tuple[mi.Float, mi.Float]:
    """Mean (m) and variance (m^2) of each lane's returned range (untruncated Gaussians, corners included).

    The variance is taken about the mean (never as ``E[z^2] - E[z]^2``, which float32 rounds by more than
    a centimetre sigma's square beyond about 40 m).
    """
    if not has_corners(seg):
        return seg.mean, dr.square(seg.sigma)
    components = _components(seg)
    shift = sum((w * (m - seg.mean) for w, m, _ in components), dr.zeros(mi.Float, dr.width(seg.mean)))
    spread = sum(
        (w * (dr.square(sd) + dr.square(m - seg.mean - shift)) for w, m, sd in components),
        dr.zeros(mi.Float, dr.width(seg.mean)),
    )
    return seg.mean + shift, spread


def _gaussian_log_density(seg: Segment, z: mi.Float) -> mi.Float:
    """Log density (1/m) of range ``z`` under each lane's truncated Gaussian (-inf outside)."""
    sigma = dr.maximum(seg.sigma, 1e-9)
    x = (z - seg.mean) / sigma
    mass = normal_cdf((seg.hi - seg.mean) / sigma) - normal_cdf((seg.lo - seg.mean) / sigma)
    uniform = -dr.log(dr.maximum(seg.hi - seg.lo, 1e-9))
    gaussian = -0.5 * x * x - dr.log(sigma) - LOG_SQRT_2PI - dr.log(dr.maximum(mass, 1e-30))
    inside = (z >= seg.lo) & (z <= seg.hi)
    value = dr.select(mass > 1e-6, gaussian, uniform)
    return dr.select(inside, value, -dr.inf)


def rotate_inverse(q: mi.Vector4f, v: mi.Vector3f) -> mi.Vector3f:
    """Rotate ``v`` by the inverse of unit quaternion ``q`` given as (x, y, z, w)."""
    u = mi.Vector3f(-q.x, -q.y, -q.z)
    return v + 2.0 * dr.cross(u, dr.cross(u, v) + q.w * v)


def ray_closest_approach(center, scale, quat, origin, direction):
    """Where the ray ``origin + t direction`` passes closest to an ellipsoid element's centre, in its metric.

    Args:
        center: (3,) lanes of ellipsoid means, m.
        scale: (3,) lanes of standard deviations along the principal axes, m.
        quat: (4,) lanes of rotations (x, y, z, w).
        origin, direction: ray origin (m) and unit direction.

    Returns:
        ``(a, t0, m2)``: the distance is ``a (t - t0)^2 + m2`` (sigmas squared): ``a`` (1/m^2), the range of
        the closest approach ``t0`` (m) and its squared distance ``m2`` (sigmas squared). ``m2`` is the
        squared norm of the perpendicular ``o + t0 d``, not ``c - b^2 / a``: float32 rounds ``c`` by 2
        sigmas squared for a 5 cm element at 250 m, which moved its chord ends by centimetres and put
        rays that miss it inside.
    """
    o, d = _element_frame(center, scale, quat, origin, direction)
    a = dr.squared_norm(d)
    t0 = -dr.dot(o, d) / a
    return a, t0, dr.squared_norm(o + t0 * d)


def _element_frame(center, scale, quat, origin, direction):
    """The ray's origin and direction in the element's frame, in its sigmas (see :func:`ray_closest_approach`)."""
    return rotate_inverse(quat, origin - center) / scale, rotate_inverse(quat, direction) / scale


def ray_restricted_gaussian(center, scale, quat, extent, origin, direction):
    """Gaussian of an ellipsoid element restricted to the ray ``origin + t direction``.

    Args:
        center, scale, quat, origin, direction: as in :func:`ray_closest_approach`.
        extent: Mahalanobis radius of the element's surface, in sigmas.

    Returns:
        ``(mean, sigma, lo, hi)``: the restricted Gaussian's mean and standard deviation in t
        (m), and the chord of the ellipsoid along the ray (m; ``lo = hi = mean`` for a ray that
        passes outside, whose gradients stay finite).
    """
    a, mean, m2 = ray_closest_approach(center, scale, quat, origin, direction)
    room = extent * extent - m2  # E^2 - m^2
    half = dr.select(room > 0, dr.sqrt(dr.maximum(room, 1e-30) / a), 0.0)
    return mean, dr.rsqrt(a), mean - half, mean + half


def corners(v0, v1, v2, triangle: mi.Bool, origin, direction, t) -> tuple[mi.Vector3f, mi.Vector3f]:
    """A triangle's corners along the ray ``origin + t direction`` that hits it at range ``t`` (m).

    Returns:
        ``(offset, weight)``: the range at which the ray passes each vertex (its projection on the
        ray) minus ``t`` (m), and the barycentric weights of the hit point (clipped to the triangle);
        zeros and ``(1, 0, 0)`` where ``triangle`` is False.
    """
    e1, e2, ep = v1 - v0, v2 - v0, origin + t * direction - v0
    d11, d12, d22 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
    d1, d2 = dr.dot(ep, e1), dr.dot(ep, e2)
    det = d11 * d22 - d12 * d12
    safe = dr.select(dr.abs(det) > 1e-20, det, 1e-20)
    b1 = dr.clip((d22 * d1 - d12 * d2) / safe, 0.0, 1.0)
    b2 = dr.clip((d11 * d2 - d12 * d1) / safe, 0.0, 1.0)
    b0 = dr.maximum(1.0 - b1 - b2, 0.0)
    total = dr.maximum(b0 + b1 + b2, 1e-12)
    weight = dr.select(triangle, mi.Vector3f(b0, b1, b2) / total, mi.Vector3f(1.0, 0.0, 0.0))
    offset = mi.Vector3f(*(dr.dot(v - origin, direction) - t for v in (v0, v1, v2)))
    return dr.select(triangle, offset, 0.0), weight


class ElementValues(NamedTuple):
    """The values of each lane's element that a :class:`Segment` carries, in its fields of the same names."""

    p: mi.Float  # probability that the element intercepts the beam
    sigma: mi.Float  # range sigma (m; the sensor's where the element has none)
    kind: mi.UInt32  # SURFACE or ELLIPSOID
    shape: mi.UInt32  # shape index in the element table
    label: mi.UInt32  # class label
    reflectivity: mi.Float  # Lambertian reflectivity


def element_segment(
    valid, element, values: ElementValues, is_ellipsoid, nominal, restricted, cos_incidence, corner
) -> Segment:
    """A :class:`Segment`: a surface returns around its nominal range; an ellipsoid its restricted Gaussian.

    Args:
        values: the element's values (its ``sigma`` is used for surfaces).
        restricted: ``(mean, sigma, lo, hi)`` of the ellipsoid Gaussian restricted to the ray (m).
        corner: ``(offset, weight)`` of :func:`corners`.
    """
    e_mean, e_sigma, e_lo, e_hi = restricted
    return Segment(
        valid=valid,
        nominal=nominal,
        mean=dr.select(is_ellipsoid, e_mean, nominal),
        lo=dr.select(is_ellipsoid, e_lo, -dr.inf),
        hi=dr.select(is_ellipsoid, e_hi, dr.inf),
        cos_incidence=cos_incidence,
        element=element,
        corner_offset=corner[0],
        corner_weight=corner[1],
        **values._replace(sigma=dr.select(is_ellipsoid, e_sigma, values.sigma))._asdict(),
    )
