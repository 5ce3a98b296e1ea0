"""``lidar_integrator``: first return through permeable elements, as a multi-channel range image."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import property_number


class LidarIntegrator(mi.SamplingIntegrator):
    r"""
    Lidar integrator (:monosp:`lidar_integrator`)
    ---------------------------------------------

    (Mitsuba keeps one namespace for all plugin types, so the integrator cannot share the name
    ``lidar`` with the sensor.)

    Traces every ray of a ``lidar`` sensor through up to ``max_segments`` elements. At each
    element a Bernoulli draw with its hit probability decides between a return and a
    pass-through; triangles return their nominal range plus Gaussian noise, ellipsoids a range
    drawn from their Gaussian restricted to the ray (see :mod:`mi_lidar.core.segment`).

    .. pluginparameters::

     * - max_segments
       - |int|
       - Elements a ray may pass through before it counts as a miss. Default: 16.
     * - effects
       - |string|
       - Physical effects applied on top of the elements, e.g.
         ``range_noise(law=proportional, sigma0=0.005, k=0.001)`` (see :mod:`mi_lidar.core.effects`).
         Their parameters are traversed as ``effects.<name>.<parameter>``. Default: none.
     * - density
       - |string|
       - The return density of every element (see :mod:`mi_lidar.core.densities`), e.g. ``gaussian``
         (default: each element's Gaussian), ``beam(...)``, or a learned model saved by
         ``mi-lidar fit-sensor``: ``np_reg(file=sensor.npz)`` (paths relative to the scene file).
         Its parameters are traversed as ``density.<name>.<parameter>``.
     * - intensity
       - |string|
       - The returned intensity in the sensor's scale, from the elements' ``reflectivity``, range,
         incidence and a per-beam gain (see :mod:`mi_lidar.core.intensity`), e.g.
         ``intensity(law=signal, gain=1000, near_range=1.5)``. Its parameters are traversed as
         ``intensity.<parameter>``. Default: ``intensity(law=reflectivity, gain=100)`` (about 100 per
         unit of reflectivity head-on, the Ouster / Velodyne calibrated scale).

    ``mi.render`` returns a tensor of shape (beams, firings, 9) whose channels are, in order,
    :data:`CHANNELS`: ``range`` (m, NaN for a miss), ``hit`` (0/1), ``element_id``, ``shape_id``
    (-1 for a miss), ``label``, ``cos_incidence``, ``nominal_range`` (m), ``segments``,
    ``intensity`` (sensor units, 0 for a miss). The same
    core serves :func:`mi_lidar.simulate`, so both paths agree ray for ray for the same seed.

    .. tabs::

        .. code-tab:: xml

            <integrator type="lidar_integrator">
                <integer name="max_segments" value="8"/>
                <string name="effects" value="range_noise(law=constant, sigma0=0.02)"/>
                <string name="intensity" value="intensity(law=reflectivity, gain=100)"/>
            </integrator>

        .. code-tab:: python

            {'type': 'lidar_integrator', 'max_segments': 8}
    """

    def __init__(self, props: mi.Properties):
        from mi_lidar.core.densities import parse_density
        from mi_lidar.core.effects import parse_effects
        from mi_lidar.core.intensity import parse_intensity

        super().__init__(props)
        self.max_segments = property_number(props, "lidar integrator", "max_segments", 16, whole=True)
        if not 1 <= self.max_segments <= 256:
            raise ParameterError(f"lidar integrator: max_segments={self.max_segments} must be in [1, 256]")
        self.effects = parse_effects(str(props.get("effects", "")))
        self.density = parse_density(
            str(props.get("density", "gaussian")), resolve=lambda name: str(mi.file_resolver().resolve(name))
        )
        self.intensity = parse_intensity(str(props.get("intensity", "")))

    def sensor_model(self, sensor):
        """The :class:`~mi_lidar.core.sensor_model.SensorModel` of ``sensor`` with this integrator's settings."""
        from mi_lidar.core.sensor_model import SensorModel

        return SensorModel(
            range_sigma=sensor.range_sigma,
            min_range=sensor.min_range,
            max_range=sensor.max_range,
            max_segments=self.max_segments,
            effects=self.effects,
            density=self.density,
            intensity=self.intensity,
        )

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        from mi_lidar.core.channels import channels_to_tensor
        from mi_lidar.core.elements import ElementTable
        from mi_lidar.core.rays import RayBatch
        from mi_lidar.plugins.lidar_sensor import LidarSensor

        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        if not isinstance(sensor, LidarSensor):
            raise ParameterError(
                f"lidar integrator: the sensor is {type(sensor).__name__}, not a `lidar` sensor; "
                'add <sensor type="lidar"> to the scene'
            )
        height, width = sensor.pattern.shape
        index = dr.arange(mi.UInt32, height * width)
        row, col = index // width, index % width
        sample2 = mi.Point2f((mi.Float(col) + 0.5) / width, (mi.Float(row) + 0.5) / height)
        ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), sample2, mi.Point2f(0.5), mi.Bool(True))
        rays = RayBatch(origin=ray.o, direction=ray.d, beam=row, time=ray.time, ray_id=index)
        model = self.sensor_model(sensor)
        out = model.simulate_rays(scene, ElementTable.from_scene(scene), rays, int(seed), evaluate=False)
        return channels_to_tensor(out, height, width)  # the last draw and the tensor: one kernel

    def traverse(self, callback):
        for effect in self.effects:
            for key, value in effect.parameters().items():
                callback.put(f"effects.{effect.name}.{key}", value, mi.ParamFlags.Differentiable)
        for key, value in self.density.parameters().items():
            callback.put(f"density.{self.density.name}.{key}", value, mi.ParamFlags.Differentiable)
        for key, value in self.intensity.parameters().items():
            callback.put(f"intensity.{key}", value, mi.ParamFlags.Differentiable)

    def aov_names(self):
        from mi_lidar.core.sensor_model import CHANNELS

        return list(CHANNELS)

    def to_string(self):
        effects = ", ".join(e.describe() for e in self.effects) or "none"
        return f"LidarIntegrator[max_segments={self.max_segments}, effects={effects}]"


mi.register_integrator("lidar_integrator", lambda props: LidarIntegrator(props))
