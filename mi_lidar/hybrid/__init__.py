"""Hybrid geometric off-road scenes (thesis ch. 4.3): synthetic worlds, fitting, primitives.

Pipeline, as a list of verbs::

    log = true_sensor.render_log(world.make_world(seed), path_poses(...))  # a labeled "real" log
    ground_mask = ground.segment_ground(points, params)               # eqs. 4.1-4.2
    model = fit.fit_model(log, params)                                # triangles + ellipsoids in blocks
    library = primitives.extract_primitives(model, log)               # objects at identity pose
    scene = compose.compose_scene(annotation, library, ground)        # a new scene
    ranges, labels = simulation.simulate_log(scene, log, seed)        # mi_lidar.simulate, the core
    table = evaluate.observation_metrics(real, ranges, origins, dirs) # thesis table 4.3

Scenes are written as Mitsuba XML + PLY with :mod:`mi_lidar.scene.files` (plus a ``lidar``
sensor and ``lidar_integrator`` when given a :class:`.blocks.SceneSensor`), so they load with
:func:`mi_lidar.load_scene` and render with ``mi.render``.
"""
