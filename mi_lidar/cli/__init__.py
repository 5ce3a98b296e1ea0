"""The ``mi-lidar`` command line: one module per verb group, one error handler (:mod:`.app`).

=====================  ==========================================================================
module                 verbs
=====================  ==========================================================================
:mod:`.render`         ``render``, ``simulate``, ``camera-lidar``, ``demo``
:mod:`.convert`        ``convert``, ``info``
:mod:`.hybrid`         ``synth-world``, ``fit-scene``, ``primitives ...``, ``annotate``, ``compose``
:mod:`.loop`           ``compare``, ``diagnose``
:mod:`.calibrate`      ``calibrate``
:mod:`.sensor`         ``fit-sensor``
:mod:`.benchmark`      ``benchmark-planar``
:mod:`.dataset`        ``dataset``
:mod:`.apps`           ``evaluate-apps``
:mod:`.apps3d`         ``evaluate-apps-3d``
=====================  ==========================================================================
"""

from mi_lidar.cli import apps, apps3d, benchmark, calibrate, convert, dataset, hybrid, loop, render, sensor  # noqa: F401  (register)
from mi_lidar.cli.app import app

__all__ = ["app"]
