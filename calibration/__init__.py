"""Calibration layer: fit scene and sensor parameters to a log by Dr.Jit autodiff (``mi-lidar calibrate``).

Imported as :mod:`mi_lidar.calibration`. Scene dicts from element sets live in :mod:`mi_lidar.scene.dicts`.
"""
