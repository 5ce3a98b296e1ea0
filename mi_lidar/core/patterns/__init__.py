"""Firing patterns: the direction, origin and timestamp of every ray of one Lidar sweep.

A :class:`FiringPattern` (module ``firing``, which states the frame and units) holds the rays of one
sweep on an ``H x W`` grid of beams by firings, as numpy arrays in radians and seconds.

Factories build the patterns of real sensors from vendor tables (:mod:`mi_lidar.core.patterns.vendor`)
and of generic scanners, one module per sensor family:

========================  ==================  ===============================================================
factory                   module              pattern
========================  ==================  ===============================================================
:func:`planar`            ``planar_scanner``  one beam sweeping a plane (SICK, Hokuyo)
:func:`spinning`          ``velodyne``        Velodyne VLP-16, HDL-32E, HDL-64E
:func:`packet_32x32`      ``velodyne``        the 32 x 32 Lidar packet of the thesis (HDL-32E)
:func:`ouster`            ``ouster_sensor``   Ouster OS-1 from its metadata JSON, or nominal OS-1-32/64/128
:func:`raster`            ``solid_state``     solid-state scanner sweeping row by row
:func:`rosette`           ``solid_state``     non-repetitive rosette of two counter-rotating prisms (Livox)
:func:`from_table`        ``table``           a user table (CSV or NPY); :func:`to_table` writes one
:func:`pattern_from_log`  ``from_log``        the exact rays of one scan of a log
========================  ==================  ===============================================================

:func:`get_pattern` (``registry``) finds any pattern by name (:data:`PATTERN_NAMES`) or by file path.

Example:
    >>> from mi_lidar.core.patterns import get_pattern
    >>> p = get_pattern("vlp16")
    >>> p.shape, round(p.period, 3)
    ((16, 1808), 0.1)
    >>> p.directions().shape
    (16, 1808, 3)
"""

from mi_lidar.core.patterns.firing import FiringPattern
from mi_lidar.core.patterns.ouster_sensor import ouster
from mi_lidar.core.patterns.planar_scanner import planar
from mi_lidar.core.patterns.registry import PATTERN_NAMES, get_pattern, is_pattern_file
from mi_lidar.core.patterns.solid_state import raster, rosette
from mi_lidar.core.patterns.table import from_table, to_table
from mi_lidar.core.patterns.velodyne import packet_32x32, spinning

__all__ = [
    "PATTERN_NAMES",
    "FiringPattern",
    "from_table",
    "get_pattern",
    "is_pattern_file",
    "ouster",
    "packet_32x32",
    "planar",
    "raster",
    "rosette",
    "spinning",
    "to_table",
]
