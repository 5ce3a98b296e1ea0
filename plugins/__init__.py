"""Mitsuba plugins of mi-lidar: the ``lidar`` sensor, the
``lidar_integrator`` and ``lidar_material``.

Importing this package registers them for the active variant. Python plugin classes derive from
the active variant's base classes, so on every variant change the modules are reloaded, which
defines and registers them again (see :func:`register`).
"""

from __future__ import annotations

import importlib

import mitsuba as mi

from mi_lidar._variant import require_jit_variant
from mi_lidar.plugins import lidar_integrator, lidar_material, lidar_sensor

_MODULES = (lidar_material, lidar_sensor, lidar_integrator)


def register() -> None:
    """(Re-)define and register every plugin for the active variant."""
    require_jit_variant(mi)
    for module in _MODULES:
        importlib.reload(module)


def _on_variant_change(old, new) -> None:
    if new is not None and not new.startswith("scalar"):
        register()


mi.detail.add_variant_callback(_on_variant_change)
