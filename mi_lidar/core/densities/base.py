"""The return-density interface: what the sensor reports for a beam that meets an element.

A :class:`ReturnDensity` maps a segment's traced state (nominal range ``seg.nominal``, incidence
``seg.cos_incidence``, label, element kind, and the ray's beam) and its own parameters to the law of
the reported range given a return, plus the probability that the element loses the beam
(``seg.drop``). It never traces; it reads features. The same object is used three ways:

* :meth:`ReturnDensity.sample`: the sampler draws a range (``mi.render``, ``mi_lidar.simulate``);
* :meth:`ReturnDensity.log_prob`: the likelihood scores a measured range (Dr.Jit, differentiable in
  the density's parameters where the family is);
* :meth:`ReturnDensity.fit`: learned families estimate their tables from traced training rays in
  closed form (P-Reg, NP-Reg); parametric ones are fitted by the one Adam fitter
  (:mod:`mi_lidar.core.fitting`) like any effect.

The order in which a segment's law is built: the element (geometry, ``p``, ``sigma`` of the
element) -> :meth:`ReturnDensity.prepare` (the family sets ``drop``, ``mean``, ``sigma`` from the
state; it never changes ``p``, the element's permeability) -> the effects' ``modify_segment``
(noise laws, bias, scale, dropouts) -> :meth:`log_prob` / :meth:`sample`. Effects that move the
location (``seg.mean``) or add Gaussian spread (``seg.sigma``) compose with every family.

A beam that meets no further element *escapes*; :meth:`ReturnDensity.escape` may give it a last,
virtual segment (``kind = ESCAPE``) whose law :meth:`ReturnDensity.prepare` sets from the escape
state (spurious returns of the classic beam model at a nominal miss). The default is no escape
segment: an escaped beam is a miss.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import Catalog, Parametrized, parse_calls
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment, log_density, sample_range, window_probability

ESCAPE = 2  # Segment.kind of the virtual segment of a beam that met nothing more


class ReturnDensity(Parametrized, metaclass=abc.ABCMeta):
    """Base class of return densities; see the module docstring for the contract."""

    kind = "density"
    learned: ClassVar[bool] = False  # estimated from traced rays and saved as tables (see from_tables)
    grid: Any = None  # the StateGrid a learned density conditions on (None: it has none)

    @classmethod
    def from_tables(cls, params: dict, grid, tables: dict) -> ReturnDensity:
        """The density of a file (:mod:`mi_lidar.core.densities.tables`): a parametric one from its parameters;
        a learned one overrides this to read its grid and tables."""
        if tables:
            raise ParameterError(f"density {cls.name!r} has no tables, but its file holds {sorted(tables)}")
        return cls(**params)

    def tables(self) -> dict:
        """The arrays saved to a density file beside the parameters (none for a parametric density)."""
        return {}

    def settings(self) -> dict:
        """Its options and every parameter (as lists of floats): what :meth:`from_tables` is built from."""
        return {**self.choices, **{k: np.asarray(v, np.float64).tolist() for k, v in self.params.items()}}

    def with_tables(self, **tables) -> ReturnDensity:
        """A copy of this learned density with the tables named in ``tables`` replaced (see :meth:`tables`)."""
        return type(self).from_tables(self.settings(), self.grid, {**self.tables(), **tables})

    def save(self, path, notes: dict | None = None):
        """Write this density to ``path`` (``.npz``; reference it as ``name(file=...)``): its options, every
        parameter, and a learned density's grid and tables."""
        from mi_lidar.core.densities.tables import save_density

        return save_density(path, self.name, self.settings(), self.grid, self.tables(), notes)

    def prepare(self, seg: Segment, rays: RayBatch) -> Segment:
        """Set the family's law of each segment from its state (default: the element's own)."""
        return seg

    @abc.abstractmethod
    def log_prob(self, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
        """Log density (1/m) of range ``z`` given a return from ``seg`` (-inf where impossible)."""

    @abc.abstractmethod
    def sample(self, seg: Segment, u: mi.Point2f, rays: RayBatch) -> mi.Float:
        """A returned range (m) per lane from two independent uniform numbers ``u.x``, ``u.y`` in [0, 1)."""

    def window(self, seg: Segment, a: float, b: float, rays: RayBatch) -> mi.Float:
        """Probability that a return from ``seg`` reports a range in ``[a, b]`` (m): the sensor's range window
        (:meth:`~mi_lidar.core.sensor_model.SensorModel.censor`). Default: the segment's own law
        (:func:`~mi_lidar.core.segment.window_probability`); a family with another law overrides it."""
        return window_probability(seg, a, b)

    def escape(self, rays: RayBatch) -> Segment | None:
        """The virtual last segment of beams that met nothing more, or None (an escaped beam is a miss)."""
        return None


class UniformEscapeDensity(ReturnDensity):
    """A density whose segments keep their own law and whose escape segment reports a range uniform on
    [0, ``z_max``] m (the spurious readings of a beam that met nothing); subclasses declare ``z_max``."""

    def log_prob(self, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
        z_max = self["z_max"]
        uniform = dr.select((z >= 0) & (z <= z_max), -dr.log(z_max), -dr.inf)
        return dr.select(seg.kind == ESCAPE, uniform, log_density(seg, z))

    def sample(self, seg: Segment, u: mi.Point2f, rays: RayBatch) -> mi.Float:
        return dr.select(seg.kind == ESCAPE, u.x * self["z_max"], sample_range(seg, u.x))

    def window(self, seg: Segment, a: float, b: float, rays: RayBatch) -> mi.Float:
        return dr.select(seg.kind == ESCAPE, uniform_window(self["z_max"], a, b), window_probability(seg, a, b))


def uniform_window(z_max, a: float, b: float) -> mi.Float:
    """Mass of the uniform law on ``[0, z_max]`` (m) within ``[a, b]`` (m)."""
    return dr.clip((dr.minimum(z_max, b) - max(a, 0.0)) / z_max, 0.0, 1.0)


def escape_segment(rays: RayBatch, drop=0.0, sigma=0.0) -> Segment:
    """The virtual segment of beams that met nothing more (``kind = ESCAPE``, nominal and mean 0).

    It goes through the density's :meth:`ReturnDensity.prepare` like a scene element (but not
    through the effects), which sets its law from the escape state.
    """
    n = rays.width
    zero = dr.zeros(mi.Float, n)
    none = dr.full(mi.UInt32, 0xFFFFFFFF, n)
    return Segment(
        valid=dr.full(mi.Bool, True, n),
        nominal=zero,
        p=zero + 1.0,
        mean=zero,
        sigma=zero + sigma,
        lo=zero - dr.inf,
        hi=zero + dr.inf,
        cos_incidence=zero + dr.nan,
        element=none,
        shape=none,
        label=dr.zeros(mi.UInt32, n),
        kind=dr.full(mi.UInt32, ESCAPE, n),
        drop=zero + drop,
    )


DENSITIES = Catalog("return density")
register_density = DENSITIES.register


def make_density(name: str, resolve=None, **values) -> ReturnDensity:
    """Instantiate catalog density ``name`` with parameter ``values``.

    A learned density is loaded from ``file=`` (a ``.npz`` written by its ``save``); ``resolve``
    maps that file name to a path (the scene folder's, in XML).
    """
    cls = DENSITIES.cls(name)
    if "file" in values:
        from mi_lidar.core.densities.tables import load_density

        path = values.pop("file")
        return load_density(resolve(path) if resolve else path, expected=cls.name, **values)
    return cls(**values)


def parse_density(spec: str, resolve=None) -> ReturnDensity:
    """Parse ``"name(key=value, ...)"`` (the integrator's ``density`` property) into one density.

    ``resolve`` maps a ``file=`` name to a path (see :func:`make_density`).
    """
    items = parse_calls(spec, lambda name, **values: make_density(name, resolve=resolve, **values), "density")
    if len(items) != 1:
        raise ParameterError(
            f"density {spec!r}: give exactly one return density, e.g. 'gaussian' or 'np_reg(file=m.npz)'"
        )
    return items[0]
