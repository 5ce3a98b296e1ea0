"""Readers and writers of Lidar scans, point clouds, images and poses.

Phase-1 writers used by ``mi-lidar render``: :func:`write_exr` (float32 multi-channel range
images), :func:`write_ply` and :func:`write_kitti_bin` (point clouds), pose files, and PNG
previews. Every writer is atomic (temporary file in the same folder, then rename).
"""

from .exr import read_exr, write_exr
from .kitti import read_kitti_bin, write_kitti_bin
from .ply import read_ply, write_ply
from .poses import read_kitti_poses, read_pose_matrices, validate_poses, write_kitti_poses
from .preview import birds_eye_png, range_image_png

__all__ = [
    "birds_eye_png",
    "range_image_png",
    "read_exr",
    "read_kitti_bin",
    "read_kitti_poses",
    "read_ply",
    "read_pose_matrices",
    "validate_poses",
    "write_exr",
    "write_kitti_bin",
    "write_kitti_poses",
    "write_ply",
]
