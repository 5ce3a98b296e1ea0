"""Scenes: Mitsuba XML / dict scenes of Lidar elements, loaded, written and simulated.

* :mod:`.loading`: ``load_scene`` with clear errors, the scene's ``lidar`` sensor and model, and
  ``bundled_scene`` (the example scenes, in a checkout or an installed wheel);
* :mod:`.files`: element PLY assets and scene XML writers;
* :mod:`.dicts`: Mitsuba scene dicts from element sets (meshes, ellipsoid sets);
* :mod:`.simulation`: the fast path, ``simulate(scene, pattern, poses)`` -> a log;
* :mod:`.camera`: a pinhole camera and synchronized camera + Lidar frames.
"""

from mi_lidar.scene.loading import (
    bundled_scene,
    load_scene,
    scene_lidar_sensor,
    scene_sensor_model,
    use_density,
    use_effects,
)

__all__ = ["bundled_scene", "load_scene", "scene_lidar_sensor", "scene_sensor_model", "use_density", "use_effects"]
