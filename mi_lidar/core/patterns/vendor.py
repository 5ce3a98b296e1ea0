"""Vendor tables of real Lidar sensors: per-laser angles, beam offsets and firing timing.

Pure data, no logic: :mod:`mi_lidar.core.patterns` turns these tables into firing patterns.
Angles are in degrees and offsets in metres, in the order of the sensor's own laser numbers
(the ``laser_id`` of the Velodyne calibration files, the pixel index of Ouster's metadata).
Spinning sensors turn clockwise seen from above; in the ROS sensor frame (x forward, y left,
z up) a laser with rotational correction ``rot`` points at azimuth ``rot - rotor_angle``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SpinningTable:
    """Geometry and timing of a multi-laser spinning Lidar.

    Attributes:
        name: Model name, e.g. ``"vlp16"``.
        elevation_deg: (L,) vertical angle of each laser, degrees, positive up.
        azimuth_offset_deg: (L,) rotational correction of each laser, degrees, counter-clockwise.
        firing_offset_s: (L,) time of each laser's pulse after the start of its firing cycle, s.
        cycle_s: Duration of one firing cycle (every laser fires once, then recharges), s.
        vertical_offset_m: (L,) beam-origin offset perpendicular to the beam in its vertical
            plane (Velodyne ``vert_offset_correction``), m; empty when the sensor has none.
        horizontal_offset_m: (L,) horizontal beam-origin offset perpendicular to the beam
            (Velodyne ``horiz_offset_correction``), m; empty when the sensor has none.
        source: Where the numbers come from.
    """

    name: str
    elevation_deg: tuple[float, ...]
    azimuth_offset_deg: tuple[float, ...]
    firing_offset_s: tuple[float, ...]
    cycle_s: float
    vertical_offset_m: tuple[float, ...] = ()
    horizontal_offset_m: tuple[float, ...] = ()
    source: str = ""


# Velodyne VLP-16 User Manual (63-9243 Rev D), section 9: lasers fire in laser-id order,
# 2.304 us apart, and the 16-laser sequence repeats every 55.296 us. Vertical angles as in
# the manual's table and in ../shared/data/velodyne/VLP16db.yaml (no rotational corrections).
VLP16 = SpinningTable(
    name="vlp16",
    elevation_deg=(-15.0, 1.0, -13.0, 3.0, -11.0, 5.0, -9.0, 7.0, -7.0, 9.0, -5.0, 11.0, -3.0, 13.0, -1.0, 15.0),
    azimuth_offset_deg=(0.0,) * 16,
    firing_offset_s=tuple(2.304e-6 * k for k in range(16)),
    cycle_s=55.296e-6,
    source="Velodyne VLP-16 User Manual 63-9243 Rev D, sec. 9 (angles and firing timing)",
)

# Velodyne HDL-32E User's Manual: lasers fire in laser-id order, 1.152 us apart, in a
# 46.08 us cycle (32 firings and a recharge). Vertical angles from the manual's table, as in
# ros-drivers/velodyne velodyne_pointcloud/params/32db.yaml (no rotational corrections).
HDL32E = SpinningTable(
    name="hdl32e",
    elevation_deg=(
        -30.67,
        -9.33,
        -29.33,
        -8.0,
        -28.0,
        -6.67,
        -26.67,
        -5.33,
        -25.33,
        -4.0,
        -24.0,
        -2.67,
        -22.67,
        -1.33,
        -21.33,
        0.0,
        -20.0,
        1.33,
        -18.67,
        2.67,
        -17.33,
        4.0,
        -16.0,
        5.33,
        -14.67,
        6.67,
        -13.33,
        8.0,
        -12.0,
        9.33,
        -10.67,
        10.67,
    ),
    azimuth_offset_deg=(0.0,) * 32,
    firing_offset_s=tuple(1.152e-6 * k for k in range(32)),
    cycle_s=46.08e-6,
    source="Velodyne HDL-32E User's Manual (angles, 1.152 us laser spacing, 46.08 us cycle)",
)

# HDL-64E S3: per-laser calibration of one unit, published in ros-drivers/velodyne,
# velodyne_pointcloud/params/64e_s3-xiesc.yaml (commit 16be7978), converted from radians to
# degrees (4 decimals) for vert_correction and rot_correction, and rounded to 0.1 mm for
# vert_offset_correction and horiz_offset_correction. Lasers 0-31 form the upper block,
# 32-63 the lower block. Timing: both blocks fire together, one laser each at a time; the
# 64 lasers are fired about 20,833 times a second (1.33 M points/s), a 48 us cycle.
# Velodyne publishes no per-laser offsets for this model, so the 32 pulses of a block are
# spread evenly over the cycle (1.5 us apart).
HDL64E = SpinningTable(
    name="hdl64e",
    elevation_deg=(
        -7.2297,
        -6.849,
        0.204,
        0.5905,
        -6.5602,
        -6.19,
        -8.5626,
        -8.2187,
        -5.8889,
        -5.483,
        -7.9432,
        -7.5522,
        -3.1191,
        -2.7921,
        -5.1346,
        -4.8091,
        -2.4882,
        -2.0906,
        -4.5299,
        -4.1573,
        -1.8098,
        -1.4588,
        -3.8193,
        -3.4693,
        0.895,
        1.2931,
        -1.1427,
        -0.7563,
        1.5623,
        1.9601,
        -0.4518,
        -0.0888,
        -22.3575,
        -21.9758,
        -11.2952,
        -10.7536,
        -21.4907,
        -21.0636,
        -24.5551,
        -24.1468,
        -20.4286,
        -19.8919,
        -23.5492,
        -22.9659,
        -16.2738,
        -15.9062,
        -19.2472,
        -18.9229,
        -15.3849,
        -14.9266,
        -18.4289,
        -17.9638,
        -14.2905,
        -13.8056,
        -17.3684,
        -16.8012,
        -10.176,
        -9.7443,
        -13.1632,
        -12.8296,
        -9.3,
        -8.7745,
        -12.294,
        -11.9133,
    ),
    azimuth_offset_deg=(
        -4.3821,
        -2.2529,
        3.4408,
        5.6834,
        -0.0546,
        2.1912,
        -0.8765,
        1.3898,
        4.2138,
        6.4847,
        3.4115,
        5.6758,
        -4.34,
        -2.1227,
        -5.1334,
        -2.9066,
        -0.1068,
        2.1474,
        -0.8706,
        1.3705,
        4.1622,
        6.3846,
        3.4048,
        5.6133,
        -4.3882,
        -2.1721,
        -5.1837,
        -2.9398,
        -0.1097,
        2.1093,
        -0.8905,
        1.3341,
        -7.326,
        -3.8118,
        5.0731,
        8.3354,
        -0.2906,
        3.1098,
        -1.6125,
        1.8176,
        6.5384,
        9.9437,
        5.4802,
        8.9028,
        -7.1125,
        -3.6746,
        -8.5214,
        -4.9889,
        -0.3896,
        3.0039,
        -1.6263,
        1.8245,
        6.2769,
        9.6696,
        5.178,
        8.5208,
        -6.9333,
        -3.6852,
        -8.3,
        -4.8844,
        -0.3419,
        2.8992,
        -1.572,
        1.6643,
    ),
    firing_offset_s=tuple(1.5e-6 * (k % 32) for k in range(64)),
    cycle_s=48e-6,
    vertical_offset_m=(
        0.2157,
        0.2152,
        0.2063,
        0.2058,
        0.2148,
        0.2144,
        0.2174,
        0.217,
        0.214,
        0.2135,
        0.2166,
        0.2161,
        0.2105,
        0.2101,
        0.213,
        0.2126,
        0.2097,
        0.2092,
        0.2123,
        0.2118,
        0.2088,
        0.2084,
        0.2114,
        0.2109,
        0.2054,
        0.205,
        0.208,
        0.2075,
        0.2046,
        0.2041,
        0.2071,
        0.2067,
        0.1597,
        0.1592,
        0.1466,
        0.146,
        0.1586,
        0.1581,
        0.1625,
        0.162,
        0.1573,
        0.1566,
        0.1612,
        0.1605,
        0.1523,
        0.1519,
        0.1558,
        0.1555,
        0.1512,
        0.1507,
        0.1549,
        0.1543,
        0.15,
        0.1494,
        0.1536,
        0.1529,
        0.1453,
        0.1448,
        0.1487,
        0.1483,
        0.1443,
        0.1437,
        0.1477,
        0.1473,
    ),
    horizontal_offset_m=(0.026, -0.026) * 32,
    source="ros-drivers/velodyne velodyne_pointcloud/params/64e_s3-xiesc.yaml (one S3 unit)",
)

# Velodyne VLP-32C User Manual (63-9325): lasers fire in pairs (ids 2k and 2k+1 together),
# 2.304 us between pairs, and the 32-laser sequence repeats every 55.296 us. Vertical angles and
# the azimuth offsets of the four laser columns from the manual's laser table.
VLP32C = SpinningTable(
    name="vlp32c",
    elevation_deg=(
        -25.0,
        -1.0,
        -1.667,
        -15.639,
        -11.31,
        0.0,
        -0.667,
        -8.843,
        -7.254,
        0.333,
        -0.333,
        -6.148,
        -5.333,
        1.333,
        0.667,
        -4.0,
        -4.667,
        1.667,
        1.0,
        -3.667,
        -3.333,
        3.333,
        2.333,
        -2.667,
        -3.0,
        7.0,
        4.667,
        -2.333,
        -2.0,
        15.0,
        10.333,
        -1.333,
    ),
    azimuth_offset_deg=(
        1.4,
        -4.2,
        1.4,
        -1.4,
        1.4,
        -1.4,
        4.2,
        -1.4,
        1.4,
        -4.2,
        1.4,
        -1.4,
        4.2,
        -1.4,
        4.2,
        -1.4,
        1.4,
        -4.2,
        1.4,
        -4.2,
        4.2,
        -1.4,
        1.4,
        -1.4,
        1.4,
        -1.4,
        1.4,
        -4.2,
        4.2,
        -1.4,
        1.4,
        -1.4,
    ),
    firing_offset_s=tuple(2.304e-6 * (k // 2) for k in range(32)),
    cycle_s=55.296e-6,
    source="Velodyne VLP-32C User Manual 63-9325 (laser angles, azimuth offsets, paired firing timing)",
)

SPINNING_TABLES: dict[str, SpinningTable] = {t.name: t for t in (VLP16, HDL32E, VLP32C, HDL64E)}

# Ouster OS-1 gen 1, 64 beams: the nominal intrinsics that the Ouster SDK uses when a sensor
# reports none (ouster-sdk, ouster_client/src/types.cpp, gen1_altitude_angles and
# gen1_azimuth_angles). The altitudes are uniform, 0.527 deg apart over +-16.611 deg; the
# azimuth offsets repeat a 4-column stagger.
OS1_GEN1_ALTITUDE_SPAN_DEG = (16.611, -16.611)
OS1_GEN1_AZIMUTH_CYCLE_DEG = (3.164, 1.055, -1.055, -3.164)

# Ouster's LiDAR frame: every beam leaves from a point this far from the z axis, in the
# direction of the encoder angle (the ouster-sdk default lidar_origin_to_beam_origin_mm for
# gen 1 sensors; a metadata file gives the exact value of a unit).
OS1_BEAM_ORIGIN_MM = 12.163

# Ouster's lidar frame -> sensor frame: a half turn about z and 36.18 mm up (translation in
# mm, row-major 4 x 4), the ouster-sdk default lidar_to_sensor_transform of OS-1 sensors and
# the value in ../shared/data/ouster/OS-1-32-G_v2.1.1_1024x10.json.
OS1_LIDAR_TO_SENSOR = (
    (-1.0, 0.0, 0.0, 0.0),
    (0.0, -1.0, 0.0, 0.0),
    (0.0, 0.0, 1.0, 36.18),
    (0.0, 0.0, 0.0, 1.0),
)
