"""Readers and writers of Lidar scans, point clouds, images and poses.

Every writer is atomic (temporary file in the same folder, then rename). Sensor logs are read
into :class:`mi_lidar.core.log.Log` with explicit misses; :func:`read_any` / :func:`write_any`
choose the format by extension (table in :mod:`mi_lidar.io.dispatch`).

=========================  ===================================================================
module                     concept
=========================  ===================================================================
:mod:`.exr`                multi-channel float32 EXR images; EXR range images of a scan
:mod:`.ply`                PLY point clouds
:mod:`.kitti`              KITTI / nuScenes ``.bin`` point files
:mod:`.pcd`                PCL ``.pcd`` point clouds
:mod:`.las`                ASPRS LAS point clouds
:mod:`.rosbag`             ROS bags of ``sensor_msgs/PointCloud2``
:mod:`.poses`              KITTI pose files and 4x4 pose matrices
:mod:`.preview`            PNG range images and bird's-eye views
:mod:`.carmen`             CARMEN planar laser logs
:mod:`.ouster`             Ouster pcap + metadata JSON
:mod:`.velodyne`           Velodyne pcap + calibration
:mod:`.cloud`              point clouds <-> ray grids (range images)
:mod:`.dispatch`           format choice by extension
:mod:`.commands`           ``convert`` and ``info`` for the CLI
=========================  ===================================================================
"""

from mi_lidar.io.carmen import read_carmen
from mi_lidar.io.cloud import cloud_from_log, log_from_points
from mi_lidar.io.commands import convert, info
from mi_lidar.io.dispatch import read_any, write_any
from mi_lidar.io.exr import read_exr, read_exr_log, write_exr, write_exr_log
from mi_lidar.io.kitti import read_bin_log, read_kitti_bin, write_bin_log, write_kitti_bin
from mi_lidar.io.las import read_las, read_las_log, write_las_log
from mi_lidar.io.ouster import range_digest, read_ouster
from mi_lidar.io.pcd import read_pcd, read_pcd_log, write_pcd, write_pcd_log
from mi_lidar.io.ply import read_ply, read_ply_log, write_ply, write_ply_log
from mi_lidar.io.poses import read_kitti_poses, read_pose_matrices, read_poses, write_kitti_poses
from mi_lidar.io.preview import birds_eye_png, range_image_png
from mi_lidar.io.rosbag import read_rosbag_log, write_rosbag_log
from mi_lidar.io.velodyne import read_velodyne

__all__ = [
    "birds_eye_png",
    "cloud_from_log",
    "convert",
    "info",
    "log_from_points",
    "range_digest",
    "range_image_png",
    "read_any",
    "read_bin_log",
    "read_carmen",
    "read_exr",
    "read_exr_log",
    "read_kitti_bin",
    "read_kitti_poses",
    "read_las",
    "read_las_log",
    "read_ouster",
    "read_pcd",
    "read_pcd_log",
    "read_ply",
    "read_ply_log",
    "read_pose_matrices",
    "read_poses",
    "read_rosbag_log",
    "read_velodyne",
    "write_any",
    "write_bin_log",
    "write_exr",
    "write_exr_log",
    "write_kitti_bin",
    "write_kitti_poses",
    "write_las_log",
    "write_pcd",
    "write_pcd_log",
    "write_ply",
    "write_ply_log",
    "write_rosbag_log",
]
