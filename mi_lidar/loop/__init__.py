"""The loop: compare a model with measurements, find the missing effect, add it, watch the error fall.

* :func:`compare`: ray-by-ray comparison and report (``mi-lidar compare``);
* :func:`diagnose`: fit every candidate effect on a training split and rank them on held-out
  rays (``mi-lidar diagnose``);
* :func:`fit_effects`: the small maximum-likelihood fitter both use.
"""

from .compare import Comparison, compare
from .diagnose import Diagnosis, diagnose
from .fit import FitResult, Problem, fit_effects
from .rays import LogRays

__all__ = ["Comparison", "Diagnosis", "FitResult", "LogRays", "Problem", "compare", "diagnose", "fit_effects"]
