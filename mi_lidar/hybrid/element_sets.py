"""Element sets of composed scenes: a primitive library filled into an annotation, ready to calibrate.

A scene composed from an annotation (:func:`mi_lidar.hybrid.compose.compose_scene`) is a
:class:`~mi_lidar.hybrid.model.HybridModel`: ground triangles plus the ellipsoids of every placed
primitive, each tagged with its object (``instance`` = annotation index + 1). Here it becomes
calibration element sets (:mod:`mi_lidar.scene.dicts`), one shape per object, so each
object's parameters have their own names, e.g. ``elements.small_tree_3.p_hit`` or
``elements.rock_0.centers``::

    sets = composed_element_sets("test_annotation.json", "library")
    scene = mi_lidar.load_scene(scene_dict(sets))        # simulate, calibrate ...
    save_scene("composed.xml", sets)                     # ... or write XML + PLY
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_lidar.hybrid.classes import CLASS_NAMES
from mi_lidar.hybrid.compose import compose_scene, load_annotation
from mi_lidar.hybrid.model import HybridModel
from mi_lidar.hybrid.primitives import PrimitiveLibrary
from mi_lidar.scene.dicts import EllipsoidElements, MeshElements

GROUND_ID = "ground"
LOOSE_ID = "ellipsoids"  # ellipsoids that belong to no object


def hybrid_element_sets(model: HybridModel) -> dict:
    """``{shape id: element set}`` of a hybrid model, one ellipsoid set per object.

    Args:
        model: ground triangles and ellipsoids; ellipsoids with ``instance`` ``i > 0`` form the
            set ``<class>_<i - 1>`` (class name of their label, ``i - 1`` the annotation index),
            the others the set ``ellipsoids``.

    Returns:
        ``ground`` (:class:`MeshElements`, per-face ``p_hit``, ``range_sigma`` (m) and ``label``)
        when the model has triangles, then the ellipsoid sets (:class:`EllipsoidElements`, extent
        ``model.extent`` sigmas) in order of object index.
    """
    sets = {}
    g, e = model.ground, model.ellipsoids
    if len(g):
        sets[GROUND_ID] = MeshElements(g.vertices, g.faces, g.p_hit, g.label, g.range_sigma)
    for instance in np.unique(e.instance):
        part = e.subset(e.instance == instance)
        scales, quaternions = part.axes()
        key = LOOSE_ID if instance <= 0 else f"{CLASS_NAMES[int(part.label[0])]}_{int(instance) - 1}"
        sets[key] = EllipsoidElements(part.means, scales, quaternions, part.p_hit, part.label, model.extent)
    return sets


def composed_element_sets(annotation, library, extent: float = 3.5, missing: str = "skip") -> dict:
    """Element sets of the scene an annotation describes, filled with a library's primitives.

    Args:
        annotation: path of an annotation JSON (see :mod:`mi_lidar.hybrid.compose`); its ground
            mesh, if any, becomes the ``ground`` set.
        library: a :class:`PrimitiveLibrary` or the folder it was saved to.
        extent: ellipsoid extent, sigmas.
        missing: ``"skip"`` leaves out objects whose class the library lacks, ``"error"`` raises
            :class:`~mi_lidar.core.errors.SceneError`.

    Returns:
        :func:`hybrid_element_sets` of the composed scene.
    """
    objects, ground = load_annotation(annotation)
    if not isinstance(library, PrimitiveLibrary):
        library = PrimitiveLibrary.load(Path(library))
    return hybrid_element_sets(compose_scene(objects, library, ground, extent, missing))
