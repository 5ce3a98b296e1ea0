"""Calibration layer: scene dicts from element sets, and (with autodiff) fitting them to logs.

Imported as :mod:`mi_lidar.calibration`.
"""

from .scene_dicts import EllipsoidElements, MeshElements, save_scene, scene_dict

__all__ = ["EllipsoidElements", "MeshElements", "save_scene", "scene_dict"]
