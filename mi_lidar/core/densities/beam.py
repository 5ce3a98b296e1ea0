"""The classic beam model (Probabilistic Robotics ch. 6.3), per state: hit, short, max and random readings.

For a beam whose element lies at range ``m`` (its nominal range plus the effects' shifts) the sensor
reports, with weights ``w = softmax(logits)`` of the beam's state:

* *hit* (``w_hit``): ``N(z; m, sigma^2)`` truncated to ``[0, z_max)``;
* *short* (``w_short``): ``lambda exp(-lambda z) / (1 - exp(-lambda m))`` on ``[0, m]`` (people, clutter);
* *max* (``w_max``): no return (the element loses the beam: ``drop``);
* *random* (``w_rand``): uniform on ``[0, z_max)``.

A beam that met nothing (the escape state) reports no return with ``w_hit + w_max`` (the hit mass
goes to the no-return point, as in Probabilistic Robotics) and otherwise a short reading truncated
at ``short_reach`` or a random one. With ``escape=own`` (default) the escape state has weights of its
own; with ``escape=shared`` it uses those of state 0. With one state and a shared escape this is the
protocol's M1 (6 parameters); on a range x incidence
:class:`~mi_lidar.core.densities.tables.StateGrid` it is M2. Every parameter is differentiable and
fitted by the one Adam fitter. Ellipsoid elements keep their own Gaussian.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.arrays import aligned
from mi_lidar.core.densities.base import ESCAPE, ReturnDensity, escape_segment, register_density, uniform_window
from mi_lidar.core.densities.tables import StateGrid
from mi_lidar.core.errors import ParameterError
from mi_lidar.core.fitting import lookup
from mi_lidar.core.params import ParamSpec
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import (
    ELLIPSOID,
    LOG_SQRT_2PI,
    Segment,
    is_open,
    log_density,
    normal_mass,
    sample_range,
    window_probability,
)

COMPONENTS = ("hit", "short", "max", "random")
START_WEIGHTS = (0.85, 0.05, 0.03, 0.07)
MIN_MASS = 1e-12  # floor of the hit Gaussian's mass on [0, z_max)


@register_density
class BeamDensity(ReturnDensity):
    """The classic beam mixture per state (see the module docstring).

    Example (XML): ``<string name="density" value="beam(file=m1.npz)"/>``; a one-state model can be
    written inline: ``beam(sigma=0.07)`` starts from the default weights.
    """

    name = "beam"
    learned = True
    options = {"escape": ("own", "shared")}
    specs = {
        "logits": ParamSpec(
            0.0, "1", "log weights of hit, short, max, random (4 per state)", lower=-20.0, upper=20.0, fit_scale=0.5
        ),
        "log_sigma": ParamSpec(
            math.log(0.05),
            "log m",
            "log of the hit sigma per state",
            lower=math.log(1e-4),
            upper=math.log(10.0),
            fit_scale=0.3,
        ),
        "log_lambda": ParamSpec(
            math.log(0.1),
            "log 1/m",
            "log of the short-reading rate per state",
            lower=math.log(1e-4),
            upper=math.log(100.0),
            fit_scale=0.3,
        ),
        "z_max": ParamSpec(80.0, "m", "largest range the sensor reports", lower=1e-3, upper=1e4, fit=False),
        "short_reach": ParamSpec(
            40.0, "m", "truncation of short readings of beams that met nothing", lower=1e-3, upper=1e4, fit=False
        ),
    }

    def __init__(self, grid: StateGrid | None = None, sigma: float | None = None, **values):
        super().__init__(**values)
        self.grid = grid or StateGrid()
        n = self.grid.size + 1
        rows = {"logits": np.log(np.asarray(START_WEIGHTS)), "log_sigma": None, "log_lambda": None}
        if sigma is not None:
            rows["log_sigma"] = np.array([math.log(sigma)])
        for key, width in (("logits", 4), ("log_sigma", 1), ("log_lambda", 1)):
            given = np.asarray(self.params[key], np.float64)
            if given.size == n * width:
                continue
            if given.size == width and key in values:
                row = given  # one state's values, given explicitly: every state starts there
            elif rows[key] is not None:
                row = rows[key]
            elif given.size == 1:
                row = np.full(width, given[0])
            else:
                raise ParameterError(
                    f"beam: {key} has {given.size} values; give {width} (one state) or {n * width} "
                    f"({n} states of the grid plus the escape state)"
                )
            self.params[key] = mi.Float(aligned(np.tile(row, n).astype(np.float32)))

    def tables(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(self.params[k]) for k in ("logits", "log_sigma", "log_lambda")}

    @classmethod
    def from_tables(cls, params: dict, grid: StateGrid | None, tables: dict) -> BeamDensity:
        return cls(grid=grid, **params, **{k: v for k, v in tables.items()})

    def save(self, path, notes: dict | None = None):
        """Write this density to ``path`` (``.npz``; reference it as ``beam(file=...)``)."""
        from mi_lidar.core.densities.tables import save_density

        params = {**self.choices, **{k: float(np.asarray(self.params[k])[0]) for k in ("z_max", "short_reach")}}
        return save_density(path, self.name, params, self.grid, self.tables(), notes)

    # ------------------------------------------------------------------ per-state values
    def state(self, seg: Segment, rays: RayBatch) -> mi.UInt32:
        inner = self.grid.index(seg.nominal, seg.cos_incidence, rays.beam, seg.label)
        escape = 0 if self.choices["escape"] == "shared" else self.grid.size
        return dr.select(seg.kind == ESCAPE, escape, inner)

    def weights(self, state: mi.UInt32) -> list[mi.Float]:
        """Softmax weights (hit, short, max, random) of each lane's state."""
        logits = [lookup(self["logits"], 4 * state + c) for c in range(4)]
        top = dr.maximum(dr.maximum(logits[0], logits[1]), dr.maximum(logits[2], logits[3]))
        exps = [dr.exp(v - top) for v in logits]
        total = exps[0] + exps[1] + exps[2] + exps[3]
        return [v / total for v in exps]

    def _rate(self, state: mi.UInt32) -> mi.Float:
        return dr.exp(lookup(self["log_lambda"], state))

    # ------------------------------------------------------------------ density interface
    def prepare(self, seg: Segment, rays: RayBatch) -> Segment:
        state = self.state(seg, rays)
        w_hit, _, w_max, _ = self.weights(state)
        escape = seg.kind == ESCAPE
        lost = dr.select(escape, w_hit + w_max, w_max)
        sigma = dr.exp(lookup(self["log_sigma"], state))
        surface = seg.kind != ELLIPSOID
        return seg.with_(
            drop=dr.select(surface, 1.0 - (1.0 - seg.drop) * (1.0 - lost), seg.drop),
            sigma=dr.select(surface, sigma, seg.sigma),
        )

    def escape(self, rays: RayBatch) -> Segment:
        return escape_segment(rays, sigma=1.0)

    def _parts(self, seg: Segment, rays: RayBatch):
        """Return weights (hit, short, random) given a return, the short reach and the rate of each lane."""
        state = self.state(seg, rays)
        w_hit, w_short, w_max, w_rand = self.weights(state)
        escape = seg.kind == ESCAPE
        w_hit = dr.select(escape, 0.0, w_hit)
        returned = dr.maximum(w_hit + w_short + w_rand, 1e-12)
        reach = dr.select(escape, self["short_reach"], dr.maximum(seg.mean, 1e-3))
        return w_hit / returned, w_short / returned, w_rand / returned, reach, self._rate(state)

    def log_prob(self, seg: Segment, z: mi.Float, rays: RayBatch) -> mi.Float:
        a_hit, a_short, a_rand, reach, rate = self._parts(seg, rays)
        z_max = self["z_max"]
        inside = (z >= 0) & (z < z_max)
        sigma = dr.maximum(seg.sigma, 1e-6)
        x = (z - seg.mean) / sigma
        # floored where float32 still squares it (the gradient divides by mass^2): an element beyond z_max
        mass = dr.maximum(normal_mass(seg.mean, sigma, 0.0, z_max), MIN_MASS)
        f_hit = dr.select(inside, dr.exp(-0.5 * x * x - LOG_SQRT_2PI) / (sigma * mass), 0.0)
        f_short = dr.select(
            (z >= 0) & (z <= reach), rate * dr.exp(-rate * z) / dr.maximum(1.0 - dr.exp(-rate * reach), 1e-12), 0.0
        )
        f_rand = dr.select(inside, 1.0 / z_max, 0.0)
        value = dr.log(dr.maximum(a_hit * f_hit + a_short * f_short + a_rand * f_rand, 1e-30))
        return dr.select(seg.kind == ELLIPSOID, log_density(seg, z), value)

    def window(self, seg: Segment, a: float, b: float, rays: RayBatch) -> mi.Float:
        if is_open(a, b):  # every component lies on [0, z_max] or [0, reach]
            return dr.select(seg.kind == ELLIPSOID, window_probability(seg, a, b), 1.0)
        a_hit, a_short, a_rand, reach, rate = self._parts(seg, rays)
        z_max = self["z_max"]
        sigma = dr.maximum(seg.sigma, 1e-6)
        low, high = max(a, 0.0), dr.minimum(z_max, b)
        mass = dr.maximum(normal_mass(seg.mean, sigma, 0.0, z_max), MIN_MASS)
        hit = dr.select(high >= low, normal_mass(seg.mean, sigma, low, high) / mass, 0.0)
        top = dr.minimum(reach, b)
        norm = dr.maximum(1.0 - dr.exp(-rate * reach), 1e-12)
        short = dr.select(top >= low, (dr.exp(-rate * low) - dr.exp(-rate * top)) / norm, 0.0)
        mixed = dr.clip(a_hit * hit + a_short * short + a_rand * uniform_window(z_max, a, b), 0.0, 1.0)
        return dr.select(seg.kind == ELLIPSOID, window_probability(seg, a, b), mixed)

    def sample(self, seg: Segment, u: mi.Point2f, rays: RayBatch) -> mi.Float:
        a_hit, a_short, a_rand, reach, rate = self._parts(seg, rays)
        z_max = self["z_max"]
        v = u.x
        hit = v < a_hit
        short = ~hit & (v < a_hit + a_short)
        truncated = seg.with_(lo=dr.zeros(mi.Float, dr.width(v)), hi=z_max + 0.0 * v)
        z_hit = sample_range(truncated, u.y)
        z_short = -dr.log(1.0 - u.y * (1.0 - dr.exp(-rate * reach))) / rate
        z_rand = u.y * z_max
        z = dr.select(hit, z_hit, dr.select(short, z_short, z_rand))
        return dr.select(seg.kind == ELLIPSOID, sample_range(seg, u.x), z)
