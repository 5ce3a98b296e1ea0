"""The effect interface: one physical effect = one small class (GUIDE section 3).

An effect has named parameters and acts through up to three hooks of the one simulation core
(:mod:`mi_lidar.core.sensor_model`):

* :meth:`Effect.perturb_rays` edits the rays before tracing (angle offsets, extrinsics);
* :meth:`Effect.modify_segment` edits each element a ray meets: its interception probability
  ``p``, the probability ``drop`` that an intercepted beam is lost, and the location ``mean`` and
  Gaussian scale ``sigma`` of the range it returns (noise laws, dropout, bias, scale);
* :meth:`Effect.finalize_range` post-processes a sampled range (quantization), with
  :meth:`Effect.likelihood_segment` as its continuous stand-in in the likelihood;
* :meth:`Effect.virtual_segments` adds elements met before the scene (outliers, clutter);
* :meth:`Effect.footprint` fans each beam out into weighted sub-rays (beam divergence), with
  :meth:`Effect.combine` forming the reported return from the sub-rays' returns in the sampler
  and :meth:`Effect.combine_log_likelihood` its likelihood from their return moments.

The **sampler** of an effect is the core's sampling loop run with these hooks; its
**log-likelihood** is the core's pass-through mixture (:mod:`mi_lidar.core.likelihood`) evaluated on
the same modified segments, so simulation and calibration always agree. Parameters are declared
with :class:`~mi_lidar.core.params.ParamSpec` (bounds, per-beam or per-label values, fitting hints)
and held as Dr.Jit arrays: enable gradients on them (``dr.enable_grad``) to fit them.

Dropouts stop the beam by default (``mode=stop``: an intercepted beam is lost, nothing behind it is
revealed, as real sensors do); ``mode=pass`` lets a dropped beam pass on to what lies behind, the
behaviour of a permeable element.

Writing a new effect::

    class RangeOffset(Effect):
        '''Constant range offset (m).'''
        name = "range_offset"
        specs = {"offset": ParamSpec(0.0, "m", "added to every return", lower=-5, upper=5, fit_scale=0.01)}

        def modify_segment(self, seg, rays):
            return seg.with_(mean=seg.mean + self["offset"])

    register_effect(RangeOffset)
"""

from __future__ import annotations

import abc
import math
from dataclasses import dataclass

import mitsuba as mi

from mi_lidar.core.params import Catalog, Parametrized, parse_calls
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment

OPEN_WINDOW = (0.0, math.inf)  # m: a sensor that reports every range


@dataclass
class SubRayMoments:
    """What the likelihood knows of each sub-ray's first return (one lane per sub-ray).

    With ``P_k = p_k prod_{j<k} (1 - p_j)`` the probability that element ``k`` returns it, the return's
    range follows the mixture ``sum_k P_k N(mean_k, sigma_k^2) / p_return``, summarised by its moments:

    Attributes:
        log_miss: ``log prod_k (1 - p_k)``, nats.
        p_return: ``sum_k P_k``.
        mean: the mixture's mean range, m (0 where ``p_return`` is 0).
        variance: the mixture's variance about ``mean``, m^2 (untruncated Gaussians; accumulated about the
            running mean, so float32 keeps a centimetre sigma at any range).
    """

    log_miss: mi.Float
    p_return: mi.Float
    mean: mi.Float
    variance: mi.Float


class Effect(Parametrized):
    """Base class of physical effects; see the module docstring for the contract."""

    kind = "effect"

    def __repr__(self) -> str:
        """As written in XML or on the command line: ``print(model.effects)`` showed object addresses."""
        return self.describe()

    @property
    def moves_rays(self) -> bool:
        """True when the effect edits rays before tracing (:meth:`perturb_rays`) or fans them out (``footprint``)."""
        cls = type(self)
        return cls.perturb_rays is not Effect.perturb_rays or cls.footprint is not Effect.footprint

    def perturb_rays(self, rays: RayBatch) -> RayBatch:
        """Edit rays before tracing (default: unchanged)."""
        return rays

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        """Edit an element met by the rays (default: unchanged)."""
        return seg

    def finalize_range(self, z: mi.Float, rays: RayBatch) -> mi.Float:
        """Post-process sampled ranges (default: unchanged)."""
        return z

    def virtual_segments(self, rays: RayBatch) -> list[Segment]:
        """Elements that are not in the scene (outliers, clutter, dust) met before it (default: none)."""
        return []

    def likelihood_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        """Likelihood-only edit: the continuous stand-in for a :meth:`finalize_range` sampler (default: unchanged)."""
        return seg

    def footprint(self, rays: RayBatch) -> tuple[RayBatch, mi.Float] | None:
        """Fan each beam out into sub-rays (default: None, one ray per beam; see :class:`FootprintEffect`)."""
        return None


class DropoutEffect(Effect):
    """An effect that keeps each intercepted beam with a probability ``keep`` and loses it otherwise.

    Subclasses implement :meth:`keep`. Option ``mode`` says what a dropped beam does:

    * ``stop`` (default): the beam is lost at the element: no return, and nothing behind it is
      revealed (``drop = 1 - (1 - drop) keep``), as with a dark, specular or grazing surface;
    * ``pass``: the element lets the beam pass to what lies behind (``p = p keep``), as a
      permeable element does.
    """

    options = {"mode": ("stop", "pass")}

    @abc.abstractmethod
    def keep(self, seg: Segment, rays: RayBatch) -> mi.Float:
        """Probability that an intercepted beam survives this effect, per lane."""

    def modify_segment(self, seg: Segment, rays: RayBatch) -> Segment:
        keep = self.keep(seg, rays)
        if self.choices["mode"] == "pass":
            return seg.with_(p=seg.p * keep)
        return seg.with_(drop=1.0 - (1.0 - seg.drop) * keep)


class FootprintEffect(Effect, metaclass=abc.ABCMeta):
    """An effect that fans each beam out into weighted sub-rays and forms one return from them.

    Subclasses implement all three methods below; a model holds at most one such effect.
    """

    @abc.abstractmethod
    def footprint(self, rays: RayBatch) -> tuple[RayBatch, mi.Float] | None:
        """Fan each beam out into sub-rays (beam divergence).

        Returns:
            ``(sub, weight)``: ``m`` sub-rays per beam, sub-ray ``j`` of beam ``i`` in lane
            ``j n + i`` (``n`` beams), sub-ray 0 along the beam's axis, and each sub-ray's share of
            the beam's energy (weights of a beam sum to 1).
        """

    @abc.abstractmethod
    def combine(self, sub: dict, weight: mi.Float, n: int, u: mi.Point2f) -> dict:
        """Form each beam's reported return from its sub-rays' first returns (sampler).

        Args:
            sub: channels of :meth:`SensorModel.simulate_rays` for the ``m n`` sub-rays.
            weight: (m n,) energy weights of the sub-rays.
            n: number of beams.
            u: (n,) two uniform numbers per beam for the effect's own random choices (which
                sub-ray reports, say), from the beam's counter-based random stream.

        Returns:
            The same channels for the ``n`` beams.
        """

    @abc.abstractmethod
    def combine_log_likelihood(
        self, moments: SubRayMoments, weight: mi.Float, z: mi.Float, hit: mi.Bool, n: int, window: tuple = OPEN_WINDOW
    ) -> mi.Float:
        """Log-likelihood (nats) of each beam's measured return from its sub-rays' return moments.

        The sensor reports only ranges in its ``window`` (the sampler drops the others): a beam's
        return law loses its mass outside to the miss, so a miss has probability ``1 - P(return) W``
        with ``W`` the law's mass in the window (:func:`~mi_lidar.core.segment.normal_mass` of its components), and a
        reported return keeps its density.

        Args:
            moments: per sub-ray, the probability of a return and the first two moments of its
                range (:class:`SubRayMoments`, ``m n`` lanes).
            weight: (m n,) energy weights of the sub-rays.
            z, hit: (n,) measured ranges (m) and return flags of the beams.
            n: number of beams.
            window: the sensor's ``(min_range, max_range)``, m.
        """


EFFECTS = Catalog("effect")
register_effect = EFFECTS.register


def make_effect(name: str, **values) -> Effect:
    """Instantiate catalog effect ``name`` with parameter ``values``."""
    return EFFECTS.cls(name)(**values)


def parse_effects(spec: str) -> list[Effect]:
    """Parse ``"name(key=value, key=[v1 v2]), other(...)"`` into effect instances.

    This is the syntax of the integrator's ``effects`` property in XML and of ``--effect`` on the
    command line. An empty string gives no effects.
    """
    return parse_calls(spec, make_effect, "effects")
