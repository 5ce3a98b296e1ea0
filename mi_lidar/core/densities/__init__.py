"""Return densities: the law of the range a sensor reports for a beam that meets an element.

See :mod:`mi_lidar.core.densities.base` for the interface. Catalog (importing this package
registers them):

=================  ==========================================================================
name               family
=================  ==========================================================================
``gaussian``       each element's truncated Gaussian (the default)
``physics``        Gaussian with sigma^2 = sigma0^2 + K r^2 / cos(incidence), constant no-return rate
``beam``           the classic beam model (hit, short, max, random) per state (M1, M2)
``p_reg``          P-Reg: P_null, mean and sigma regressed on range and incidence (thesis 3.3)
``np_reg``         NP-Reg: per-state residual histograms smoothed across states (thesis 3.4; M3)
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
from mi_lidar.core.densities.beam import BeamDensity
from mi_lidar.core.densities.gaussian import ElementGaussian
from mi_lidar.core.densities.histogram import NPRegDensity
from mi_lidar.core.densities.physics import PhysicsDensity
from mi_lidar.core.densities.preg import PRegDensity

__all__ = [
    "DENSITIES",
    "ESCAPE",
    "BeamDensity",
    "ElementGaussian",
    "NPRegDensity",
    "PRegDensity",
    "PhysicsDensity",
    "ReturnDensity",
    "make_density",
    "parse_density",
    "register_density",
]
