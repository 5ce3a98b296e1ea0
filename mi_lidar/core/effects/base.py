"""The effect interface: one physical effect = one small class (GUIDE section 3).

An effect has named parameters and acts through up to three hooks of the one simulation core
(:mod:`mi_lidar.core.sensor_model`):

* :meth:`Effect.perturb_rays` edits the rays before tracing (angle offsets, extrinsics);
* :meth:`Effect.modify_segment` edits each element a ray meets: its hit probability ``p`` and
  the Gaussian ``N(mean, sigma^2)`` of the range it returns (noise laws, dropout, bias, scale);
* :meth:`Effect.finalize_range` post-processes a sampled range (quantization), with
  :meth:`Effect.likelihood_segment` as its continuous stand-in in the likelihood;
* :meth:`Effect.virtual_segments` adds elements met before the scene (outliers, clutter);
* :meth:`Effect.footprint` fans each beam out into weighted sub-rays (beam divergence), with
  :meth:`Effect.combine` forming the reported return from the sub-rays' returns in the sampler
  and :meth:`Effect.combine_log_likelihood` its likelihood from their return moments.

The **sampler** of an effect is the core's sampling loop run with these hooks; its
**log-likelihood** is the core's pass-through mixture ``-log sum_k P_k N(z; mean_k, sigma_k)``
evaluated on the same modified segments, so simulation and calibration always agree. Parameters
are Dr.Jit arrays: enable gradients on them (``dr.enable_grad``) to fit them.

Writing a new effect::

    class RangeOffset(Effect):
        '''Constant range offset (m).'''
        name = "range_offset"
        specs = {"offset": ParamSpec(0.0, "m", "added to every return")}

        def modify_segment(self, seg, rays):
            return seg.with_(mean=seg.mean + self["offset"])

    register_effect(RangeOffset)
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import ClassVar

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment


@dataclass(frozen=True)
class ParamSpec:
    """Declaration of one effect parameter.

    Attributes:
        default: default value (scalar) or None when the parameter is required.
        unit: physical unit, for documentation and reports.
        doc: one-line meaning.
        lower, upper: allowed closed range (checked on construction).
        per_beam: the parameter holds one value per beam (a list in XML).
        fit_lower: lower bound kept while fitting, when above ``lower``: a scale whose variance is
            quadratic in it (a noise sigma) has zero gradient at 0, so an optimizer that reaches
            0 would stay there whatever the data say.
    """

    default: float | None
    unit: str
    doc: str
    lower: float = -np.inf
    upper: float = np.inf
    per_beam: bool = False
    fit_lower: float | None = None

    @property
    def fit_bound(self) -> float:
        """The lower bound of fitted values: ``fit_lower`` if set, else ``lower``."""
        return self.lower if self.fit_lower is None else max(self.lower, self.fit_lower)


@dataclass
class SubRayMoments:
    """What the likelihood knows of each sub-ray's first return (one lane per sub-ray).

    With ``P_k = p_k prod_{j<k} (1 - p_j)`` the probability that element ``k`` returns it:

    Attributes:
        log_miss: ``log prod_k (1 - p_k)``, nats.
        p_return: ``sum_k P_k``.
        m1: ``sum_k P_k mean_k``, m.
        m2: ``sum_k P_k (sigma_k^2 + mean_k^2)``, m^2 (untruncated Gaussians).
    """

    log_miss: mi.Float
    p_return: mi.Float
    m1: mi.Float
    m2: mi.Float


class Effect:
    """Base class of physical effects; see the module docstring for the contract."""

    name: ClassVar[str] = ""
    specs: ClassVar[dict[str, ParamSpec]] = {}
    options: ClassVar[dict[str, tuple[str, ...]]] = {}

    def __init__(self, **values):
        unknown = sorted(set(values) - set(self.specs) - set(self.options))
        if unknown:
            allowed = sorted(set(self.specs) | set(self.options))
            raise ParameterError(f"effect {self.name!r}: unknown parameter(s) {unknown}; allowed: {allowed}")
        self.choices = {}
        for key, allowed in self.options.items():
            choice = str(values.get(key, allowed[0]))
            if choice not in allowed:
                raise ParameterError(f"effect {self.name!r}: {key}={choice!r}; choose one of {list(allowed)}")
            self.choices[key] = choice
        self.params: dict[str, mi.Float] = {}
        for key, spec in self.specs.items():
            raw = values.get(key, spec.default)
            if raw is None:
                raise ParameterError(f"effect {self.name!r}: parameter {key!r} ({spec.doc}, {spec.unit}) is required")
            array = np.atleast_1d(np.asarray(raw, dtype=np.float64))
            bad = ~np.isfinite(array) | (array < spec.lower) | (array > spec.upper)
            if np.any(bad):
                raise ParameterError(
                    f"effect {self.name!r}: {key}={array[bad][0]:g} {spec.unit} is outside "
                    f"[{spec.lower:g}, {spec.upper:g}] ({spec.doc})"
                )
            self.params[key] = mi.Float(array.astype(np.float32))

    def __getitem__(self, key: str) -> mi.Float:
        return self.params[key]

    def per_beam(self, key: str, beam: mi.UInt32) -> mi.Float:
        """Value of per-beam parameter ``key`` for each lane's beam (the last value repeats)."""
        values = self.params[key]
        return dr.gather(mi.Float, values, dr.minimum(beam, dr.width(values) - 1))

    def parameters(self) -> dict[str, mi.Float]:
        """Named parameters (Dr.Jit arrays) for traversal and fitting."""
        return self.params

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

    def describe(self) -> str:
        """``name(key=value, ...)``: the effect as written in XML or on the command line."""
        parts = [f"{k}={v}" for k, v in self.choices.items()]
        for key, value in self.params.items():
            array = np.asarray(value)
            parts.append(
                f"{key}={array[0]:.6g}" if array.size == 1 else f"{key}=[{' '.join(f'{x:.6g}' for x in array)}]"
            )
        return f"{self.name}({', '.join(parts)})"


class FootprintEffect(Effect, metaclass=abc.ABCMeta):
    """An effect that fans each beam out into weighted sub-rays and forms one return from them.

    Subclasses implement all three methods below; a model holds at most one such effect.
    """

    @abc.abstractmethod
    def footprint(self, rays: RayBatch) -> tuple[RayBatch, mi.Float] | None:
        """Fan each beam out into sub-rays (beam divergence).

        Returns:
            ``(sub, weight)``: ``m`` sub-rays per beam, sub-ray ``j`` of beam ``i`` in lane
            ``j n + i`` (``n`` beams), and each sub-ray's share of the beam's energy (weights of a
            beam sum to 1).
        """

    @abc.abstractmethod
    def combine(self, sub: dict, weight: mi.Float, n: int) -> dict:
        """Form each beam's reported return from its sub-rays' first returns (sampler).

        Args:
            sub: channels of :meth:`SensorModel.simulate_rays` for the ``m n`` sub-rays.
            weight: (m n,) energy weights of the sub-rays.
            n: number of beams.

        Returns:
            The same channels for the ``n`` beams.
        """

    @abc.abstractmethod
    def combine_log_likelihood(
        self, moments: SubRayMoments, weight: mi.Float, z: mi.Float, hit: mi.Bool, n: int
    ) -> mi.Float:
        """Log-likelihood (nats) of each beam's measured return from its sub-rays' return moments.

        Args:
            moments: per sub-ray, the probability of a return and the first two moments of its
                range (:class:`SubRayMoments`, ``m n`` lanes).
            weight: (m n,) energy weights of the sub-rays.
            z, hit: (n,) measured ranges (m) and return flags of the beams.
            n: number of beams.
        """


EFFECTS: dict[str, type[Effect]] = {}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Add an effect class to the catalog under ``cls.name`` (usable as a decorator)."""
    if not cls.name:
        raise ParameterError(f"effect class {cls.__name__} needs a non-empty `name`")
    EFFECTS[cls.name] = cls
    return cls


def make_effect(name: str, **values) -> Effect:
    """Instantiate catalog effect ``name`` with parameter ``values``."""
    if name not in EFFECTS:
        raise ParameterError(f"unknown effect {name!r}; the catalog has: {', '.join(sorted(EFFECTS)) or 'none'}")
    return EFFECTS[name](**values)


def _parse_value(text: str):
    text = text.strip()
    if text.startswith("[") and text.endswith("]"):
        return [float(x) for x in text[1:-1].replace(",", " ").split()]
    try:
        return float(text)
    except ValueError:
        return text


def parse_effects(spec: str) -> list[Effect]:
    """Parse ``"name(key=value, key=[v1 v2]), other(...)"`` into effect instances.

    This is the syntax of the integrator's ``effects`` property in XML and of ``--effect`` on
    the command line. An empty string gives no effects.
    """
    effects, rest = [], spec.strip()
    while rest:
        name, sep, tail = rest.partition("(")
        name = name.strip().strip(",;").strip()
        if not sep:
            effects.append(make_effect(name))
            break
        body, closing, rest = tail.partition(")")
        if not closing:
            raise ParameterError(f"effects {spec!r}: missing ')' after {name}(")
        values, depth, current = {}, 0, ""
        for char in body + ",":
            depth += char == "["
            depth -= char == "]"
            if char == "," and depth == 0:
                if current.strip():
                    key, eq, value = current.partition("=")
                    if not eq:
                        raise ParameterError(f"effects {spec!r}: expected key=value in {current.strip()!r}")
                    values[key.strip()] = _parse_value(value)
                current = ""
            else:
                current += char
        effects.append(make_effect(name, **values))
        rest = rest.strip().lstrip(",;").strip()
    return effects
