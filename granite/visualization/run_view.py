"""rerun view of a VO run: live while ``granite run`` processes frames, completed at the end.

During the run each frame logs the image, the tracks coloured by inverse distance and the time
series. When the run ends (or for a finished run folder, see :mod:`granite.cli.view_cmd`), the
estimate is Sim(3)-aligned to the ground truth per sub-map and the aligned camera, keyframes
and trajectory are logged for every frame on the same timeline.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from granite.errors import GraniteError
from granite.evaluation import ate
from granite.visualization.rerun_logger import ESTIMATE_COLOR, GROUNDTRUTH_COLOR, KEYFRAME_COLOR, RerunLogger


def aligned_poses(traj, ground_truth) -> np.ndarray:
    """Estimate poses Sim(3)-aligned to the ground truth per sub-map; NaN where a pose could
    not be aligned (outside the ground truth, or an unalignable sub-map). Unaligned without
    ground truth."""
    if ground_truth is None:
        return np.array(traj.poses)
    out = np.full(traj.poses.shape, np.nan)
    try:
        aligned = ate(traj, ground_truth, align="sim3").aligned
    except GraniteError:
        return out
    index = {float(t): k for k, t in enumerate(traj.timestamps)}
    for t, pose in zip(aligned.timestamps, aligned.poses):
        out[index[float(t)]] = pose
    return out


class LiveRunView:
    def __init__(self, dataset, rrd_path: str | Path | None, spawn: bool = False, name: str | None = None):
        self.log = RerunLogger(name or f"granite-run-{dataset.name}", rrd_path, spawn)
        calib = dataset.calibration
        if calib is not None:
            i = calib.intrinsics
            self.log.log_camera_model(i["fx"], i["fy"], i["cx"], i["cy"], calib.width, calib.height)
        if dataset.ground_truth is not None:
            self.log.log_trajectory("world/groundtruth", dataset.ground_truth.positions, GROUNDTRUTH_COLOR)
        self._keyframes: list[tuple[int, tuple[int, ...]]] = []
        self._landmarks: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._timestamps: dict[int, float] = {}

    def log_frame(self, frame, out) -> None:
        log = self.log
        log.set_frame(frame.index, frame.timestamp)
        self._timestamps[frame.index] = frame.timestamp
        if frame.image is not None:
            log.log_image(frame.image)
        if out.tracks is not None and len(out.tracks):
            log.log_tracks(out.tracks.positions, out.tracks.levels, out.track_inverse_distance)
        d = out.diagnostics
        log.log_scalar("tracked_points", d.tracked_points)
        log.log_scalar("finite_landmarks", d.finite_landmarks)
        log.log_scalar("infinite_landmarks", d.infinite_landmarks)
        log.log_scalar("keyframe", float(d.keyframe))
        log.log_scalar("submap", d.submap)
        if d.negative_entropy is not None:
            log.log_scalar("negative_entropy", d.negative_entropy)
        self._keyframes.append((frame.index, out.keyframe_ids))

    def finish(self, result, ground_truth) -> None:
        """Log the aligned estimate for every frame and the aligned trajectory."""
        traj = result.trajectory
        poses = aligned_poses(traj, ground_truth)
        index_of = {int(d.frame_index): k for k, d in enumerate(result.diagnostics)}
        self.log.log_trajectory("world/estimate", poses[:, :3, 3], ESTIMATE_COLOR)
        for frame_index, kf_ids in self._keyframes:
            k = index_of.get(frame_index)
            if k is None or not np.all(np.isfinite(poses[k])):
                continue
            self.log.set_frame(frame_index, float(traj.timestamps[k]))
            self.log.log_camera_pose(poses[k])
            kf_pos = [poses[index_of[f], :3, 3] for f in kf_ids if f in index_of]
            if kf_pos:
                self.log.log_points3d("world/keyframes", np.array(kf_pos), KEYFRAME_COLOR, radius=0.05)
        self.log.close()
