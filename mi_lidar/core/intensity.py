"""Returned intensity: what a sensor reports for the strength of a return, from the element's reflectivity.

A Lambertian element of reflectivity ``rho`` at range ``r`` and incidence ``delta`` returns the
power ``P ~ rho cos(delta) / r^2`` (the Lidar equation), times the receiver's *near-field* overlap
``o(r) = 1 - exp(-(r / near_range)^2)`` (a coaxial receiver sees little of a close target) and a
per-beam gain. Sensors report it in one of two scales (option ``law``):

* ``signal``: the raw return, ``I = gain_b rho cos^a o(r) (R0 / r)^n`` with ``R0`` =
  :data:`REFERENCE_RANGE`, so ``gain_b`` is what beam ``b`` reports for a white target seen head-on
  at 10 m (Ouster SIGNAL, photon counts);
* ``reflectivity``: the sensor compensates the range falloff, ``I = gain_b rho cos^a o(r)`` (Ouster
  REFLECTIVITY and the Velodyne VLP-16's calibrated reflectivity, 0-255: about 100 rho for a diffuse
  target, above 100 for retroreflectors).

The reported value is Gaussian about ``I`` with ``sigma^2 = noise_floor^2 + (noise_relative I)^2``,
except for a fraction ``p_outlier`` of returns whose value is uniform on ``[0, max_value]`` (edges
mixing two surfaces, glints), rounded to the sensor's integer units and clipped to ``[0, max_value]``
when sampled. On real frames the spread is mostly relative: between neighbouring Ouster columns the
median |difference| is 20-30 % of the value over two decades of REFLECTIVITY and SIGNAL.
The likelihood scores a measured intensity by that Gaussian's density per unit, the probability of
its one-unit bin as long as ``sigma`` is not below the spread of rounding (``1 / sqrt(12)`` units,
the noise floor's lower bound while fitting). It does so inside the pass-through mixture: the return
from element ``k`` has the joint density
``f_k(z) g_k(I)`` (:func:`mi_lidar.core.likelihood.mixture_log_likelihood`), so the element that
explains the range also has to explain the intensity. Everything is differentiable in the model's
parameters and in the elements' reflectivities (:attr:`~mi_lidar.core.elements.ElementTable.reflectivity`).

Example: ``intensity(law=signal, gain=[900 ... 1100], near_range=1.5)``.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import Parametrized, ParamSpec, parse_calls
from mi_lidar.core.rays import RayBatch
from mi_lidar.core.segment import Segment

REFERENCE_RANGE = 10.0  # m: the range at which `gain` is the raw signal of a white target (law=signal)
ROUNDING_SIGMA = 1.0 / math.sqrt(12.0)  # units: the spread of rounding to integers, the least noise a fit may find


def _gain_scale(model: IntensityModel) -> float:
    """Step unit of the gain: a tenth of its current mean (its size depends on the sensor's scale)."""
    return max(0.1 * float(np.mean(np.asarray(model.params["gain"]))), 1e-3)


class IntensityModel(Parametrized):
    """The returned intensity of a segment (see the module docstring for the laws)."""

    name = "intensity"
    kind = "intensity model"
    options = {"law": ("reflectivity", "signal")}
    specs = {
        "gain": ParamSpec(
            100.0,
            "units",
            "intensity beam b reports for a white target head-on (at 10 m for law=signal)",
            lower=0.0,
            upper=1e7,
            per_beam=True,
            fit_scale=_gain_scale,
        ),
        "incidence_exponent": ParamSpec(
            1.0, "1", "exponent a of cos(incidence) (1 = Lambertian)", lower=0.0, upper=10.0, fit_scale=0.1
        ),
        "range_exponent": ParamSpec(
            2.0,
            "1",
            "exponent n of the range falloff (2 = extended target)",
            lower=0.0,
            upper=6.0,
            fit_scale=0.1,
            only={"law": ("signal",)},
        ),
        "near_range": ParamSpec(
            0.5,
            "m",
            "near-field range: the receiver sees 63 % of a target at this range (0: no falloff)",
            lower=0.0,
            upper=50.0,
            fit_scale=0.2,
            fit_lower=0.01,
        ),
        "noise_floor": ParamSpec(
            2.0,
            "units",
            "standard deviation of the reported value at zero intensity",
            lower=0.0,
            fit_lower=ROUNDING_SIGMA,
        ),
        "noise_relative": ParamSpec(
            0.1, "1", "standard deviation proportional to the intensity", lower=0.0, upper=10.0, fit_lower=1e-3
        ),
        "p_outlier": ParamSpec(
            0.01,
            "1",
            "fraction of returns with a value uniform on [0, max_value]",
            lower=0.0,
            upper=0.5,
            fit_scale=0.01,
            fit_lower=1e-4,
        ),
        "max_value": ParamSpec(255.0, "units", "largest value the sensor reports", lower=1.0, fit=False),
    }

    def white_target(self, nominal: mi.Float, cos_incidence: mi.Float, beam: mi.UInt32) -> mi.Float:
        """Noise-free intensity (sensor units) of a white diffuse target (``rho = 1``) per lane.

        Args:
            nominal: range to the target, m.
            cos_incidence: |cos| of the incidence angle.
            beam: beam index of each lane (selects the per-beam gain).
        """
        r = dr.maximum(nominal, 1e-3)
        cos = dr.clip(cos_incidence, 1e-4, 1.0)
        near = self["near_range"]
        overlap = 1.0 - dr.exp(-dr.square(r / dr.maximum(near, 1e-6)))
        power = self.per_beam("gain", beam) * dr.exp(self["incidence_exponent"] * dr.log(cos))
        if self.choices["law"] == "signal":
            power = power * dr.exp(self["range_exponent"] * dr.log(REFERENCE_RANGE / r))
        return power * overlap

    def expected(self, seg: Segment, rays: RayBatch) -> mi.Float:
        """Noise-free intensity ``I`` (sensor units) of each lane's segment."""
        return self.white_target(seg.nominal, seg.cos_incidence, rays.beam) * seg.reflectivity

    def apparent_reflectivity(
        self, intensity: np.ndarray, nominal: np.ndarray, cos_incidence: np.ndarray, beam: np.ndarray
    ) -> np.ndarray:
        """The law inverted: the reflectivity that returns ``intensity`` at this range, incidence and beam.

        Args:
            intensity: (N,) measured intensities, sensor units.
            nominal: (N,) ranges, m.
            cos_incidence: (N,) |cos| of the incidence angles (of the surface the return is assigned to).
            beam: (N,) beam indices.

        Returns:
            (N,) reflectivities (1 = white diffuse target); 0 where the law predicts no power.
        """
        white = np.asarray(
            self.white_target(
                mi.Float(np.asarray(nominal, np.float32)),
                mi.Float(np.asarray(cos_incidence, np.float32)),
                mi.UInt32(np.asarray(beam, np.uint32)),
            ),
            np.float64,
        )
        return np.where(white > 0, np.asarray(intensity, np.float64) / np.maximum(white, 1e-30), 0.0)

    def sigma(self, mean: mi.Float) -> mi.Float:
        """Standard deviation (sensor units) of the reported value about ``mean``."""
        return dr.sqrt(dr.square(self["noise_floor"]) + dr.square(self["noise_relative"] * mean) + 1e-12)

    def log_prob(self, seg: Segment, intensity: mi.Float, rays: RayBatch) -> mi.Float:
        """Log density (per sensor unit) of a measured ``intensity`` given a return from ``seg``."""
        mean = self.expected(seg, rays)
        sigma = self.sigma(mean)
        x = (intensity - mean) / sigma
        gaussian = dr.exp(-0.5 * x * x) / (sigma * math.sqrt(2.0 * math.pi))
        outlier = self["p_outlier"]
        return dr.log((1.0 - outlier) * gaussian + outlier / self["max_value"] + 1e-30)

    def sample(self, seg: Segment, u: mi.Float, rays: RayBatch) -> mi.Float:
        """A reported intensity per lane from one uniform number ``u`` in [0, 1) (integer units, clipped)."""
        mean = self.expected(seg, rays)
        outlier = self["p_outlier"]
        v = dr.clip((u - outlier) / (1.0 - outlier), 1e-7, 1.0 - 1e-7)  # uniform again above p_outlier
        value = mean + self.sigma(mean) * math.sqrt(2.0) * dr.erfinv(2.0 * v - 1.0)
        value = dr.select(u < outlier, u / dr.maximum(outlier, 1e-12) * self["max_value"], value)
        return dr.clip(dr.round(value), 0.0, self["max_value"])


def parse_intensity(spec: str) -> IntensityModel:
    """Parse ``"intensity(key=value, ...)"`` (the integrator's ``intensity`` property) into a model.

    An empty string gives the default model (``law=reflectivity``, gain 100).
    """

    def make(name: str, **values) -> IntensityModel:
        if name != IntensityModel.name:
            raise ParameterError(f"intensity model {name!r}: write intensity(...), e.g. intensity(law=signal)")
        return IntensityModel(**values)

    items = parse_calls(spec, make, "intensity")
    if len(items) > 1:
        raise ParameterError(f"intensity {spec!r}: give one intensity model, e.g. intensity(law=signal)")
    return items[0] if items else IntensityModel()
