"""``lidar`` sensor: emits a real Lidar firing pattern; its film is the range image."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_lidar.core.errors import ParameterError
from mi_lidar.core.params import (
    DISTANCE_LIMIT,
    MAX_DISTANCE_M,
    MAX_SIGMA_M,
    SIGMA_LIMIT,
    check_limit,
    property_number,
)
from mi_lidar.core.poses import validate_poses


class LidarSensor(mi.Sensor):
    r"""
    Lidar sensor (:monosp:`lidar`)
    ------------------------------

    .. pluginparameters::

     * - pattern
       - |string|
       - Firing pattern: a name (``vlp16``, ``hdl32e``, ``hdl64e``, ``os1-32``, ``os1-64``,
         ``os1-128``, ``planar-360``, ``planar-180``, ``packet32``, ``raster``, ``rosette``) or
         the path of a table (``.csv``/``.npy``) or of an Ouster metadata ``.json``.
         Default: ``vlp16``.
     * - firings
       - |int|
       - Firings per sweep (film width) for spinning and planar patterns. Default: the pattern's.
     * - min_range
       - |float|
       - Returns closer than this are not reported (m; the blind zone), up to 1e8 m. Default: 0.
     * - max_range
       - |float|
       - Elements farther than this are not seen, and returns reported beyond it are not
         reported (m): the sampler and the likelihood lose them alike. Up to 1e8 m (a larger
         number is a misread one), or ``inf`` for no far end. Default: 120.
     * - range_sigma
       - |float|
       - Range noise (m) of elements that do not set their own, up to 1000 m (a larger one spreads
         every return over the whole range window: a misread number). Default: 0.01.
     * - to_world
       - |transform|
       - Sensor pose: sensor frame (x forward, y left, z up) to world, a finite rigid transform
         (rotation and translation, no scale). Not differentiable here
         (calibrate extrinsics with :mod:`mi_lidar.calibration`).

    The film is the range image: width = firings, height = beams (rows sorted by elevation,
    highest first). When no film is given, a float32 ``hdrfilm`` of that size with a box filter
    is created; a film of another size is an error. Each ray carries its firing timestamp in
    ``ray.time`` (s since the sweep start).

    .. tabs::

        .. code-tab:: xml

            <sensor type="lidar">
                <string name="pattern" value="vlp16"/>
                <float name="max_range" value="100"/>
                <transform name="to_world"><translate z="1.8"/></transform>
            </sensor>

        .. code-tab:: python

            {'type': 'lidar', 'pattern': 'vlp16', 'max_range': 100.0,
             'to_world': mi.ScalarTransform4f().translate([0, 0, 1.8])}
    """

    def __init__(self, props: mi.Properties):
        from mi_lidar.core.patterns import get_pattern

        name = str(props.get("pattern", "vlp16"))
        kwargs = (
            {"n_firings": property_number(props, "lidar sensor", "firings", 0, whole=True)}
            if "firings" in props
            else {}
        )
        if name.endswith((".csv", ".npy", ".json")):  # a table next to the scene file
            name = str(mi.file_resolver().resolve(name))
        self.pattern = get_pattern(name, **kwargs)
        height, width = self.pattern.shape
        if "film" not in props:
            props["film"] = mi.load_dict(
                {
                    "type": "hdrfilm",
                    "width": width,
                    "height": height,
                    "rfilter": {"type": "box"},
                    "pixel_format": "luminance",
                    "component_format": "float32",
                }
            )
        super().__init__(props)
        film_size = tuple(int(v) for v in self.film().size())
        if film_size != (width, height):
            raise ParameterError(
                f"lidar sensor: film is {film_size[0]} x {film_size[1]} but pattern {name!r} fires "
                f"{width} x {height} (firings x beams); remove the <film> or set width={width}, height={height}"
            )
        self.min_range = property_number(props, "lidar sensor", "min_range", 0.0)
        self.max_range = property_number(props, "lidar sensor", "max_range", 120.0)
        self.range_sigma = property_number(props, "lidar sensor", "range_sigma", 0.01)
        self.to_world_matrix = validate_poses(
            np.array(props.get("to_world", mi.ScalarTransform4f()).matrix, dtype=np.float64), "lidar sensor: to_world"
        )[0]
        self.to_world = mi.ScalarTransform4f(self.to_world_matrix.astype(np.float32))
        fix = "fix the value in the scene"
        check_limit("lidar sensor", "min_range", self.min_range, MAX_DISTANCE_M, DISTANCE_LIMIT, fix)
        check_limit("lidar sensor", "max_range", self.max_range, MAX_DISTANCE_M, DISTANCE_LIMIT, fix, open_end=True)
        if not self.min_range < self.max_range:
            raise ParameterError(
                f"lidar sensor: need min_range < max_range; got min_range={self.min_range}, "
                f"max_range={self.max_range}; fix the values in the scene"
            )
        check_limit("lidar sensor", "range_sigma", self.range_sigma, MAX_SIGMA_M, SIGMA_LIMIT, fix)
        self.local_directions = mi.Vector3f(*np.ascontiguousarray(self.pattern.directions().reshape(-1, 3).T))
        self.local_origins = mi.Point3f(*np.ascontiguousarray(self.pattern.origins().reshape(-1, 3).T))
        self.times = mi.Float(self.pattern.time.reshape(-1).astype(np.float32))

    def pixel_index(self, sample2: mi.Point2f) -> mi.UInt32:
        """Row-major index of the range-image pixel that film position ``sample2`` falls in."""
        height, width = self.pattern.shape
        col = dr.clip(mi.UInt32(sample2.x * width), 0, width - 1)
        row = dr.clip(mi.UInt32(sample2.y * height), 0, height - 1)
        return row * width + col

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        index = self.pixel_index(sample2)
        to_world = mi.Transform4f(self.to_world)
        direction = to_world @ dr.gather(mi.Vector3f, self.local_directions, index, active)
        origin = to_world @ dr.gather(mi.Point3f, self.local_origins, index, active)
        ray = mi.Ray3f(
            origin, dr.normalize(direction), time + dr.gather(mi.Float, self.times, index, active), mi.Color0f()
        )
        ray.maxt = self.max_range
        return ray, mi.Spectrum(1.0)

    def to_string(self):
        height, width = self.pattern.shape
        return f"LidarSensor[pattern={self.pattern.name!r}, beams={height}, firings={width}]"


mi.register_sensor("lidar", lambda props: LidarSensor(props))
