"""The sampler's random numbers: counter-based streams, independent or correlated between neighbouring beams.

Every random choice of the sampler (:mod:`mi_lidar.core.sensor_model`) is one uniform number keyed by
(seed, ray id, segment, stream). With an integer seed the numbers are a TEA hash of the key
(:func:`uniform`): independent between rays, and the same whichever rays are traced together.

A real scanner's errors are not independent between neighbouring beams: along a wall the residual
of neighbouring beams is nearly the same (the wall is straight, the map's error is shared) and stray
returns come in runs (a person's legs, a door frame). :class:`NeighbourStreams` draws every stream
through a Gaussian copula whose latent normal scores are correlated along each scan's beams:

    g_b = sqrt(w) a_b + sqrt(1 - w) e_b,    a_b = rho a_(b-1) + sqrt(1 - rho^2) d_b

with ``a`` a stationary AR(1) process restarted at each scan's first beam and ``d``, ``e`` independent
standard normals, so ``corr(g_b, g_(b+k)) = w rho^k``: a share ``w`` of every draw is shared over about
``1 / (1 - rho)`` beams. Each uniform number is ``Phi(g_b)``, exactly uniform, so every beam's
distribution (and the likelihood, which scores beams one by one) is unchanged; only the joint law of
a scan changes. Different (segment, stream) keys get independent latent processes, so the draws
within one beam stay independent. The outcome of every segment has its own stream; the draws of the
reported range and intensity (streams 1 and up) are the same for every segment of a ray, since at
most one segment of a ray reports, so neighbouring beams share them even where their returns come
from different segments (a stray cell before the wall of one beam, not of the next). With ``w = 0``
the outcome numbers are those of :func:`uniform` and every beam's draws are independent of its
neighbours'.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.errors import ParameterError

MAX_UNIFORM = 1.0 - 2.0**-24  # largest float32 below 1: Phi of a large score must stay in [0, 1)
DECISION_STREAM = 0  # the stream that decides an element's outcome (one per segment)
DRIVE_STREAM = 64  # offset of the stream that drives a stream's shared (AR(1)) part
MAX_SEED = 2**32 - 1  # the streams key on the seed modulo 2**32: a larger seed would repeat a smaller one's draws


def uniform(seed, ray_id: mi.UInt32, segment, stream: int) -> mi.Float:
    """Uniform numbers in [0, 1): one per lane, keyed by (seed, ray, segment, stream).

    ``seed`` is an integer from 0 to :data:`MAX_SEED` (the counter-based TEA hash) or a :class:`NeighbourStreams`.
    ``segment`` is a Python int or a per-lane ``mi.UInt32`` (the counter of a symbolic loop); both
    give the same numbers, as the key is formed modulo 2^32 either way.

    The sampler's entry points check the seed first (:func:`check_seed`): raised in here, inside a Dr.Jit loop,
    the error would come out as the loop's RuntimeError.
    """
    if isinstance(seed, NeighbourStreams):
        return seed.uniform(ray_id, segment, stream)
    base = (int(seed) * 0x9E3779B1 + stream * 0xC2B2AE3D) & 0xFFFFFFFF
    if isinstance(segment, int):
        # An opaque key is a kernel input, not a constant: new seeds and rounds reuse compiled kernels.
        return mi.sample_tea_float32(ray_id, dr.opaque(mi.UInt32, (base + segment * 0x85EBCA77) & 0xFFFFFFFF), 8)
    return mi.sample_tea_float32(ray_id, dr.opaque(mi.UInt32, base) + segment * 0x85EBCA77, 8)


def check_seed(seed) -> None:
    """Refuse an integer seed outside 0 .. :data:`MAX_SEED`: :func:`uniform` keys on it modulo 2**32, so seed 2**32
    gave the very scan of seed 0 (labelled 2**32), and seed -1 that of 2**32 - 1. A :class:`NeighbourStreams`
    was checked when it was made.

    Raises:
        ParameterError: naming the seed, the range and the seed it would repeat.
    """
    if not isinstance(seed, NeighbourStreams) and not 0 <= int(seed) <= MAX_SEED:
        raise ParameterError(
            f"seed {seed} is outside 0 .. {MAX_SEED}: the random streams key on 32 bits, so it would repeat the "
            f"draws of seed {int(seed) % 2**32}; give a seed in that range"
        )


def uniforms(seed, ray_id: mi.UInt32, segment) -> mi.Point2f:
    """The two uniform numbers a return density draws a range from (streams 1 and 2 of :func:`uniform`)."""
    return mi.Point2f(uniform(seed, ray_id, segment, 1), uniform(seed, ray_id, segment, 2))


@dataclass(frozen=True)
class BeamCorrelation:
    """How much of a beam's random draws it shares with its neighbours (see the module docstring).

    Attributes:
        shared: ``w`` in [0, 1), the variance share of the latent score common to neighbouring beams.
        rho: ``rho`` in [0, 1), the lag-one correlation of the shared part (it spans ~1 / (1 - rho) beams).
    """

    shared: float = 0.0
    rho: float = 0.0

    def __post_init__(self) -> None:
        for name in ("shared", "rho"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0 or not np.isfinite(value):
                raise ParameterError(f"BeamCorrelation: {name} must be in [0, 1), got {value!r}")

    def lag(self, k: np.ndarray) -> np.ndarray:
        """Correlation of the latent scores of beams ``k`` (>= 1) apart in one scan: ``w rho^k``."""
        return self.shared * self.rho ** np.asarray(k, np.float64)

    @property
    def active(self) -> bool:
        return self.shared > 0.0


@dataclass
class NeighbourStreams:
    """Uniform streams correlated along each scan's beams (a Gaussian copula; see the module docstring).

    Attributes:
        seed: the seed of the independent draws the copula transforms.
        follows: (N,) bool per ray id: ray ``i`` is the next beam of ray ``i - 1``'s scan (ray ids are
            ``0 .. N - 1``; ``follows[0]`` is False).
        correlation: the shared variance and its lag-one correlation.
    """

    seed: int
    follows: np.ndarray
    correlation: BeamCorrelation
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        check_seed(int(self.seed))

    def uniform(self, ray_id: mi.UInt32, segment, stream: int) -> mi.Float:
        """The stream's numbers of rays ``ray_id`` (a Python int ``segment`` only: the trace's rounds)."""
        if not isinstance(segment, int):
            raise TypeError("NeighbourStreams: the segment must be a Python int (use it with sample_trace)")
        key = (segment if stream == DECISION_STREAM else 0, stream)
        if key not in self._cache:
            self._cache[key] = self._draw(*key)
        return dr.gather(mi.Float, self._cache[key], ray_id)

    def _draw(self, segment: int, stream: int) -> mi.Float:
        """(N,) correlated uniform numbers of one (segment, stream) for every ray id."""
        n = self.follows.size
        ids = dr.arange(mi.UInt32, n)
        if not self.correlation.active:
            return uniform(self.seed, ids, segment, stream)
        w, rho = self.correlation.shared, self.correlation.rho
        own, drive = (_scores(uniform(self.seed, ids, segment, s)) for s in (stream, stream + DRIVE_STREAM))
        shared = ar1(drive, self.follows, rho)
        score = np.sqrt(w) * shared + np.sqrt(1.0 - w) * own
        from scipy.special import ndtr  # scipy on first use: `import mi_lidar` stays fast

        return mi.Float(aligned(np.clip(ndtr(score), 0.0, MAX_UNIFORM).astype(np.float32)))


def _scores(u: mi.Float) -> np.ndarray:
    """Standard normal scores (float64) of uniform numbers."""
    from scipy.special import ndtri

    return ndtri(np.clip(np.asarray(u, np.float64), 1e-12, MAX_UNIFORM))


def ar1(drive: np.ndarray, follows: np.ndarray, rho: float) -> np.ndarray:
    """A stationary AR(1) process of unit variance driven by standard normals ``drive`` (N,), restarted where
    ``follows`` is False: ``a_0 = d_0``, ``a_i = rho a_(i-1) + sqrt(1 - rho^2) d_i``."""
    from scipy.signal import lfilter

    x = np.sqrt(1.0 - rho * rho) * drive
    starts = ~np.asarray(follows, bool)
    x[starts] = drive[starts]
    out = np.empty_like(x)
    bounds = np.append(np.flatnonzero(starts), x.size)
    for a, b in zip(bounds[:-1], bounds[1:]):
        out[a:b] = lfilter([1.0], [1.0, -rho], x[a:b])
    return out


def scan_follows(scan: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """(N,) True where ray ``i`` is beam ``beam[i - 1] + 1`` of the same scan as ray ``i - 1``."""
    scan, beam = np.asarray(scan), np.asarray(beam)
    out = np.zeros(scan.size, bool)
    out[1:] = (scan[1:] == scan[:-1]) & (beam[1:] == beam[:-1] + 1)
    return out
