"""A small primitive library for tests that need one on disk (datasets, reader fuzzing)."""

from pathlib import Path

import numpy as np

from mi_lidar.hybrid.classes import CLASS_ID
from mi_lidar.hybrid.model import EllipsoidSet
from mi_lidar.hybrid.primitives import Primitive, PrimitiveLibrary


def small_library(folder: Path) -> None:
    """Write a library of two primitives to ``folder``: a ``tree`` (small_tree) and a ``rock``."""

    def primitive(name, label, means, sigma, p_hit):
        means = np.asarray(means, float)
        covs = np.tile(np.diag([sigma**2, (0.8 * sigma) ** 2, (1.3 * sigma) ** 2]), (len(means), 1, 1))
        ellipsoids = EllipsoidSet(means, covs, np.full(len(means), p_hit), label=label)
        return Primitive(name, label, ellipsoids, means.min(0) - 3 * sigma, means.max(0) + 3 * sigma)

    PrimitiveLibrary(
        [
            primitive("tree", CLASS_ID["small_tree"], [[0, 0, -1.0], [0, 0, 0.2], [0.3, 0.2, 1.2]], 0.4, 0.5),
            primitive("rock", CLASS_ID["rock"], [[0, 0, 0], [0.4, 0, 0.1]], 0.25, 0.9),
        ]
    ).save(folder)
