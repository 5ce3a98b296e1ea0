"""The registry of pattern names: :func:`get_pattern` builds any pattern by name or from a file."""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable
from pathlib import Path

from mi_lidar.core.errors import PatternError
from mi_lidar.core.patterns.firing import FiringPattern
from mi_lidar.core.patterns.ouster_sensor import ouster
from mi_lidar.core.patterns.planar_scanner import planar
from mi_lidar.core.patterns.solid_state import raster, rosette
from mi_lidar.core.patterns.table import from_table
from mi_lidar.core.patterns.velodyne import packet_32x32, spinning

_REGISTRY: dict[str, tuple[Callable[..., FiringPattern], dict]] = {
    "planar-360": (planar, {"n_bearings": 360, "fov_deg": 360.0}),
    "planar-180": (planar, {"n_bearings": 180, "fov_deg": 180.0}),
    "vlp16": (spinning, {"model": "vlp16"}),
    "hdl32e": (spinning, {"model": "hdl32e"}),
    "vlp32c": (spinning, {"model": "vlp32c"}),
    "hdl64e": (spinning, {"model": "hdl64e"}),
    "os1-32": (ouster, {"beams": 32}),
    "os1-64": (ouster, {"beams": 64}),
    "os1-128": (ouster, {"beams": 128}),
    "packet32": (packet_32x32, {}),
    "raster": (raster, {}),
    "rosette": (rosette, {}),
}

PATTERN_NAMES: tuple[str, ...] = tuple(_REGISTRY)
"""Names accepted by :func:`get_pattern`."""


PATTERN_FILE_SUFFIXES = (".csv", ".npy", ".json")


def is_pattern_file(name_or_path: str | os.PathLike) -> bool:
    """Whether :func:`get_pattern` reads ``name_or_path`` as a file (a table or Ouster metadata), not a name."""
    return Path(os.fspath(name_or_path)).suffix.lower() in PATTERN_FILE_SUFFIXES


def get_pattern(name_or_path: str | os.PathLike, **kwargs) -> FiringPattern:
    """Build a firing pattern by name or from a file.

    Args:
        name_or_path: One of :data:`PATTERN_NAMES` (case-insensitive), or a path ending in
            ``.csv``/``.npy`` (:func:`from_table`) or ``.json`` (Ouster metadata,
            :func:`ouster`).
        **kwargs: Parameters of the factory, overriding the preset of the name, e.g.
            ``get_pattern("vlp16", rpm=1200)`` or ``get_pattern("planar-180", period=0.2)``.

    Returns:
        The pattern.

    Raises:
        PatternError: Unknown name or parameter, or any error of the factory.
    """
    text = os.fspath(name_or_path)
    suffix = Path(text).suffix.lower()
    factory: Callable[..., FiringPattern]
    if suffix in (".csv", ".npy"):
        factory, preset = from_table, {"path": text}
    elif suffix == ".json":
        factory, preset = ouster, {"metadata": text}
    elif text.lower() in _REGISTRY:
        factory, preset = _REGISTRY[text.lower()]
    else:
        raise PatternError(
            f"unknown firing pattern {text!r}; choose one of {', '.join(PATTERN_NAMES)}, "
            "or give a .csv/.npy table or an Ouster .json metadata file"
        )
    accepted = inspect.signature(factory).parameters
    unknown = sorted(set(kwargs) - set(accepted))
    if unknown:
        raise PatternError(
            f"pattern {text!r} does not take {', '.join(unknown)}; its parameters are {', '.join(accepted)}"
        )
    return factory(**{**preset, **kwargs})
