"""mi-lidar: Lidar simulation for robot application development on Mitsuba 3 / Dr.Jit.

Importing the package finds a suitable LLVM, activates the ``llvm_ad_rgb`` variant (or
``$MI_LIDAR_VARIANT``) unless a JIT variant is already active, and registers the plugins.
"""

from ._variant import configure_llvm

configure_llvm()

import mitsuba as mi  # noqa: E402  (LLVM must be configured before Dr.Jit loads)

from ._variant import select_variant  # noqa: E402

__version__ = "0.1.0"
VARIANT = select_variant(mi)

from .log import Log  # noqa: E402

__all__ = ["Log", "VARIANT", "__version__"]
