"""mi-lidar: Lidar simulation for robot application development on Mitsuba 3 / Dr.Jit.

Importing the package finds a suitable LLVM, activates the ``llvm_ad_rgb`` variant (or
``$MI_LIDAR_VARIANT``) unless a JIT variant is already active, and registers the plugins
(``lidar`` sensor, ``lidar_integrator``, ``lidar_material``).
"""

from mi_lidar._variant import configure_llvm

configure_llvm()

import mitsuba as mi  # noqa: E402  (LLVM must be configured before Dr.Jit loads)

from mi_lidar._variant import exit_if_command_line, select_variant  # noqa: E402
from mi_lidar.core.errors import SetupError  # noqa: E402

__version__ = "0.1.0"
try:
    VARIANT = select_variant(mi)
except SetupError as error:
    exit_if_command_line(error)
    raise

from mi_lidar import plugins  # noqa: E402,F401  (registers the plugins)
from mi_lidar.core.log import Log  # noqa: E402
from mi_lidar.core.sensor_model import CHANNELS, SensorModel  # noqa: E402
from mi_lidar.scene.loading import load_scene  # noqa: E402
from mi_lidar.scene.simulation import simulate  # noqa: E402

__all__ = ["CHANNELS", "Log", "SensorModel", "VARIANT", "__version__", "load_scene", "simulate"]
