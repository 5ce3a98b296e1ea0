"""nuScenes calibration pickles (mmdetection3d info files): the Lidar and camera mounts of one keyframe.

The file is a pickled dict of numpy scalars and arrays; it is read with a restricted unpickler that
refuses every class except numpy's array and scalar reconstructors, so a crafted file cannot run code.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError

NUSCENES_IMAGE_SIZE = (1600, 900)  # width, height of every nuScenes camera, pixels
_ALLOWED = {
    ("numpy", "dtype"),
    ("numpy", "ndarray"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("_codecs", "encode"),
}


class _NumpyOnly(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}: only numpy arrays and scalars are allowed")
        return super().find_class(module, name)


def read_nuscenes_calibration(path: str | os.PathLike, sample: int = 0) -> dict:
    """The sensor calibration of one keyframe of a nuScenes info pickle.

    Args:
        path: the ``.pkl`` info file.
        sample: index in its ``data_list``.

    Returns:
        ``{"lidar2ego": (4, 4), "ego2global": (4, 4), "cameras": {name: {"K": (3, 3) pixel
        intrinsics, "cam2ego": (4, 4) OpenCV optical frame (x right, y down, z forward) to ego,
        "width": 1600, "height": 900}}}``; ego is x forward, y left, z up, metres.

    Raises:
        LogFormatError: missing or unreadable file, or a file without these fields.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFormatError(f"{path}: no such nuScenes info file")
    try:
        with open(path, "rb") as stream:
            info = _NumpyOnly(stream).load()
        entry = info["data_list"][sample]
        width, height = NUSCENES_IMAGE_SIZE
        return {
            "lidar2ego": np.asarray(entry["lidar_points"]["lidar2ego"], dtype=np.float64),
            "ego2global": np.asarray(entry["ego2global"], dtype=np.float64),
            "cameras": {
                name: {
                    "K": np.asarray(camera["cam2img"], dtype=np.float64)[:3, :3],
                    "cam2ego": np.asarray(camera["cam2ego"], dtype=np.float64),
                    "width": width,
                    "height": height,
                }
                for name, camera in entry["images"].items()
            },
        }
    except (pickle.UnpicklingError, KeyError, IndexError, TypeError, EOFError) as exc:
        raise LogFormatError(
            f"{path}: not a nuScenes info pickle with lidar2ego and camera calibration: {exc}"
        ) from exc
