"""File formats: trajectories (TUM, EuRoC), calibration (Basalt JSON), images, datasets
(EuRoC/ASL, test-bench output, TUM RGB-D, KITTI) and atomic output.

Every reader validates its input and raises :class:`granite.errors.InputError` naming the
file and, where it applies, the 1-based line. Every writer is atomic (:mod:`.atomic`).
"""

from granite.io.atomic import PendingFile, atomic_path, atomic_write_bytes, atomic_write_text, check_writable
from granite.io.calibration import (
    CAMERA_PARAMS,
    RADTAN,
    Calibration,
    parse_calibration,
    read_calibration,
    write_calibration,
)
from granite.io.dataset import FORMATS, Dataset, Frame, open_dataset
from granite.io.euroc import (
    SensorInfo,
    ns_from_seconds,
    read_euroc_groundtruth,
    read_euroc_image_list,
    read_sensor_yaml,
    seconds_from_ns,
    write_euroc_groundtruth,
    write_euroc_image_list,
    write_sensor_yaml,
)
from granite.io.images import read_image
from granite.io.kitti import (
    format_kitti_poses,
    read_kitti_intrinsics,
    read_kitti_poses,
    read_kitti_projection,
    read_kitti_times,
    write_kitti_poses,
)
from granite.io.run_folder import attach_submaps, read_estimate, read_submaps
from granite.io.trajectory_file import detect_trajectory_format, read_trajectory
from granite.io.tum import format_tum, parse_tum, read_tum, write_tum
from granite.io.tum_rgbd import read_tum_rgbd_list
from granite.io.undistortion import Undistortion

__all__ = [
    "CAMERA_PARAMS",
    "RADTAN",
    "FORMATS",
    "Calibration",
    "Dataset",
    "Frame",
    "PendingFile",
    "Undistortion",
    "SensorInfo",
    "atomic_path",
    "attach_submaps",
    "atomic_write_bytes",
    "atomic_write_text",
    "check_writable",
    "detect_trajectory_format",
    "format_kitti_poses",
    "format_tum",
    "ns_from_seconds",
    "open_dataset",
    "parse_calibration",
    "parse_tum",
    "read_calibration",
    "read_estimate",
    "read_euroc_groundtruth",
    "read_euroc_image_list",
    "read_image",
    "read_kitti_intrinsics",
    "read_kitti_projection",
    "read_kitti_poses",
    "read_kitti_times",
    "read_sensor_yaml",
    "read_submaps",
    "read_trajectory",
    "read_tum",
    "read_tum_rgbd_list",
    "seconds_from_ns",
    "write_calibration",
    "write_euroc_groundtruth",
    "write_euroc_image_list",
    "write_kitti_poses",
    "write_sensor_yaml",
    "write_tum",
]
