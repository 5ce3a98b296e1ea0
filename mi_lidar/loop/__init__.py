"""The loop: compare a model with measurements, find the missing effect, add it, watch the error fall.

* :func:`compare`: ray-by-ray comparison and report (``mi-lidar compare``);
* :func:`diagnose`: fit every candidate effect on a training split and rank them on held-out
  rays (``mi-lidar diagnose``);
"""

from mi_lidar.core.rays import LogRays
from mi_lidar.loop.compare import Comparison, compare
from mi_lidar.loop.diagnose import Diagnosis, diagnose

__all__ = ["Comparison", "Diagnosis", "LogRays", "compare", "diagnose"]
