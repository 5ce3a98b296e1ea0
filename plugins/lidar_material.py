"""``lidar_material``: per-shape Lidar properties, nested in a shape as its BSDF."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import MAX_SIGMA_M, SIGMA_LIMIT, check_limit, property_number

MAX_LABEL = 2**24  # labels reach the range image in float32 channels, exact up to 2**24 (2**24 + 1 read as 2**24)


class LidarMaterial(mi.BSDF):
    r"""
    Lidar material (:monosp:`lidar_material`)
    -----------------------------------------

    .. pluginparameters::

     * - p_hit
       - |float|
       - Probability (0 to 1) that the element returns a beam that meets it; otherwise the beam
         passes through (permeable vegetation, glass, dust). Default: 1 (opaque). Differentiable
         through :class:`mi_lidar.core.elements.ElementTable`.
     * - range_sigma
       - |float|
       - Standard deviation (m) of the range returned by this shape's triangles, up to 1000 m. Default:
         the sensor's ``range_sigma``. Ellipsoids return their own Gaussian restricted to the ray.
     * - label
       - |int|
       - Class label reported for returns from this shape (a whole number from 0 to 2**24). Default: 0.
     * - reflectance
       - |float|
       - Diffuse albedo (0 to 1) seen by cameras, so one scene serves camera and Lidar. Default: 0.5.
     * - reflectivity
       - |float|
       - Lambertian reflectivity at the Lidar's wavelength (0 black, 1 white diffuse target, above 1
         for retroreflectors, at most 100). It sets the returned intensity and weak-return dropout
         (:mod:`mi_lidar.core.intensity`, ``reflectivity_dropout``). Default: ``reflectance`` (a
         camera albedo seeds it when no Lidar data exist). Fitted per element by
         ``mi_lidar.calibration.intensity``.

    Per-element values stored in the shape's PLY (``p_hit_0``, ``range_sigma_0``, ``label_0``,
    ``reflectivity_0``) take precedence over these per-shape values.

    .. tabs::

        .. code-tab:: xml

            <shape type="ply" id="hedge">
                <string name="filename" value="hedge.ply"/>
                <bsdf type="lidar_material">
                    <float name="p_hit" value="0.3"/>
                    <integer name="label" value="4"/>
                    <float name="reflectivity" value="0.12"/>
                </bsdf>
            </shape>

        .. code-tab:: python

            {'type': 'lidar_material', 'p_hit': 0.3, 'label': 4, 'reflectivity': 0.12}
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.p_hit = property_number(props, "lidar_material", "p_hit", 1.0)
        self.range_sigma = property_number(props, "lidar_material", "range_sigma", math.nan)
        self.label = property_number(props, "lidar_material", "label", 0, whole=True)
        self.reflectance = property_number(props, "lidar_material", "reflectance", 0.5)
        self.reflectivity = property_number(props, "lidar_material", "reflectivity", self.reflectance)
        checks = [
            ("p_hit", self.p_hit, 0.0 <= self.p_hit <= 1.0, "[0, 1]"),
            ("label", self.label, 0 <= self.label <= MAX_LABEL, f"[0, 2**24 = {MAX_LABEL}] (float32's whole numbers)"),
            ("reflectance", self.reflectance, 0.0 <= self.reflectance <= 1.0, "[0, 1]"),
            ("reflectivity", self.reflectivity, 0.0 <= self.reflectivity <= 100.0, "[0, 100]"),
        ]
        fix = "fix the value in the scene"
        for name, value, ok, allowed in checks:
            if not ok:
                raise ParameterError(f"lidar_material: {name}={value} is outside {allowed}; {fix}")
        # unset (NaN): the sensor's range_sigma
        check_limit("lidar_material", "range_sigma", self.range_sigma, MAX_SIGMA_M, SIGMA_LIMIT, fix, unset_nan=True)
        self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]

    def sample(self, ctx, si, sample1, sample2, active=True):
        cos_i = mi.Frame3f.cos_theta(si.wi)
        bs = mi.BSDFSample3f()
        bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = mi.UInt32(0)
        ok = active & (cos_i > 0) & (bs.pdf > 0)
        return bs, dr.select(ok, mi.Spectrum(self.reflectance), 0.0)

    def eval(self, ctx, si, wo, active=True):
        ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
        return dr.select(ok, mi.Spectrum(self.reflectance * dr.inv_pi) * mi.Frame3f.cos_theta(wo), 0.0)

    def pdf(self, ctx, si, wo, active=True):
        ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
        return dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def eval_attribute_1(self, name, si, active=True):
        values = {
            "p_hit": self.p_hit,
            "range_sigma": self.range_sigma,
            "label": float(self.label),
            "reflectivity": self.reflectivity,
        }
        if name not in values:
            raise ParameterError(f"lidar_material has no attribute {name!r}; use one of {sorted(values)}")
        return mi.Float(values[name])

    def to_string(self):
        return (
            f"LidarMaterial[p_hit={self.p_hit}, range_sigma={self.range_sigma}, label={self.label}, "
            f"reflectivity={self.reflectivity}]"
        )


mi.register_bsdf("lidar_material", lambda props: LidarMaterial(props))
