"""Return densities: the law of the range a sensor reports for a beam that meets an element.

See :mod:`mi_lidar.core.densities.base` for the interface. Catalog (importing this package
registers them):

=================  ==========================================================================
name               family
=================  ==========================================================================
``gaussian``       each element's truncated Gaussian (the default)
=================  ==========================================================================
"""

from mi_lidar.core.densities.base import (
    DENSITIES,
    ESCAPE,
    ReturnDensity,
    make_density,
    parse_density,
    register_density,
)
from mi_lidar.core.densities.gaussian import ElementGaussian

__all__ = [
    "DENSITIES",
    "ESCAPE",
    "ElementGaussian",
    "ReturnDensity",
    "make_density",
    "parse_density",
    "register_density",
]
