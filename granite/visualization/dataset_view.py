"""rerun recording of a dataset without any VO: images, the ground-truth trajectory and the
camera as a posed frustum per frame (and depth maps, when the caller can read them).

Same entity layout and timelines as a run (:mod:`granite.visualization.rerun_logger`), plus
``world/camera/depth`` (planar depth, metres). Frames whose image cannot be read
still get their ground-truth pose; frames dropped by a test-bench flight have no row in the
image list, so they show only on the ground-truth line.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from granite.geometry import interpolate_poses
from granite.io import Dataset
from granite.visualization.rerun_logger import GROUNDTRUTH_COLOR, RerunLogger

#: ``depth_of(frame_index)`` -> (H, W) metres (``inf``: no surface) or None.
DepthReader = Callable[[int], "np.ndarray | None"]


def log_dataset(
    dataset: Dataset,
    rrd_path: str | Path | None = None,
    spawn: bool = False,
    depth_of: DepthReader | None = None,
    progress: Callable[[Iterable], Iterable] = lambda frames: frames,
    warn: Callable[[str], None] | None = None,
) -> dict[str, int]:
    """Write a recording of ``dataset`` to ``rrd_path`` (or stream it, ``spawn``). Returns
    counts: frames, images, poses (ground truth at the frame time), depth maps. ``warn(text)``
    is told about every image that cannot be used. On an error no file is written."""
    log = RerunLogger(f"granite-dataset-{dataset.name}", rrd_path, spawn)
    try:
        counts = _log_frames(log, dataset, depth_of, progress, warn)
    except BaseException:
        log.discard()
        raise
    log.close()
    return counts


def _log_frames(log: RerunLogger, dataset: Dataset, depth_of: DepthReader | None,
                progress: Callable[[Iterable], Iterable], warn: Callable[[str], None] | None) -> dict[str, int]:
    calib = dataset.calibration
    if calib is not None:
        i = calib.intrinsics
        log.log_camera_model(i["fx"], i["fy"], i["cx"], i["cy"], calib.width, calib.height)
    gt = dataset.ground_truth
    poses = None
    if gt is not None:
        log.log_trajectory("world/groundtruth", gt.positions, GROUNDTRUTH_COLOR)
        inside = (dataset.timestamps >= gt.timestamps[0]) & (dataset.timestamps <= gt.timestamps[-1])
        poses = np.full((len(dataset), 4, 4), np.nan)
        if inside.any():
            poses[inside] = interpolate_poses(gt.timestamps, gt.poses, dataset.timestamps[inside])
    counts = {"frames": 0, "images": 0, "poses": 0, "depth_maps": 0}
    posed: list[int] = []
    for frame in progress(dataset.frames()):
        log.set_frame(frame.index, frame.timestamp)
        counts["frames"] += 1
        if frame.image is not None:
            log.log_image(frame.image, frame.path)
            counts["images"] += 1
        elif warn is not None:
            warn(f"frame {frame.index}: image skipped: {frame.error} ({frame.path})")
        if poses is not None and np.isfinite(poses[frame.index]).all():
            posed.append(frame.index)
        depth = depth_of(frame.index) if depth_of is not None else None
        if depth is not None:
            log.log_depth(np.where(np.isfinite(depth), depth, 0.0).astype(np.float32))
            counts["depth_maps"] += 1
    if posed:
        log.send_camera_poses(posed, dataset.timestamps[posed], poses[posed])
    counts["poses"] = len(posed)
    return counts
