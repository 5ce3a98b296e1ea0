"""The core Lidar model: pure functions and small classes on Dr.Jit arrays and numpy.

It knows nothing of files, reports or the command line (those layers import it, never the
reverse): firing patterns (:mod:`.patterns`), logs (:mod:`.log`), rays (:mod:`.rays`), the element
table of a scene (:mod:`.elements`), segments and their return distributions (:mod:`.segment`),
effects (:mod:`.effects`), and the sensor model that samples and scores returns
(:mod:`.sensor_model`).
"""
