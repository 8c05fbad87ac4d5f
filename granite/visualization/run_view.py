"""rerun view of a VO run, live while ``granite run`` processes frames or afterwards from a run
folder (``granite view``); both go through :class:`RunView`.

Per frame the image, the tracks coloured by inverse distance and the time series are logged as
they come. When the run ends, the estimate is Sim(3)-aligned to the ground truth per sub-map
(the paper's Fig. 3) and the aligned camera, the window's keyframes and landmarks and the
aligned trajectory are logged for every frame on the same timeline, and, with ground truth,
the running relative scale error (``plots/relative_scale_error``, over ``scale_delta`` seconds;
:mod:`granite.evaluation.scale_drift`). Until then the window landmarks of every frame wait in
temporary files (:class:`LandmarkSpool`) and are sent in chunks of frames, so a recording's
memory does not grow with the run's length.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from granite.errors import GraniteError
from granite.estimator.diagnostics import FrameDiagnostics
from granite.estimator.records import FrameRecord
from granite.evaluation import ate, relative_scale_error
from granite.trajectory import Trajectory
from granite.visualization.colors import inverse_distance_colors
from granite.visualization.rerun_logger import (
    ESTIMATE_COLOR,
    GROUNDTRUTH_COLOR,
    RerunLogger,
)


def similarity_per_submap(traj: Trajectory, ground_truth: Trajectory | None) -> dict[int, tuple]:
    """Sim(3) ``(s, R, t)`` per sub-map aligning the estimate to the ground truth (identity
    without ground truth; sub-maps that cannot be aligned are missing)."""
    ids = np.unique(traj.submap) if traj.submap is not None else np.array([0])
    if ground_truth is None:
        return {int(i): (1.0, np.eye(3), np.zeros(3)) for i in ids}
    try:
        return ate(traj, ground_truth, align="sim3").transforms
    except GraniteError:
        return {}


def _apply(sim, points: np.ndarray) -> np.ndarray:
    s, R, t = sim
    return s * points @ R.T + t


def _aligned_pose(sim, T_w_c: np.ndarray) -> np.ndarray:
    """``T_w_c`` moved by the similarity ``sim`` (the camera frame itself is not scaled)."""
    T = np.eye(4)
    T[:3, :3] = sim[1] @ T_w_c[:3, :3]
    T[:3, 3] = _apply(sim, T_w_c[:3, 3][None])[0]
    return T


class LandmarkSpool:
    """The window landmarks of every frame (float32 world points (M_i, 3) and inverse
    distances (M_i,), as ``landmarks.npz`` stores them) in two anonymous temporary files,
    read back frame by frame in the order they were appended. ``folder``: where the files live
    (they have no name and vanish when closed; default the system's temporary folder)."""

    def __init__(self, folder: str | Path | None = None):
        self._xyz = tempfile.TemporaryFile(dir=folder)
        self._inverse_distance = tempfile.TemporaryFile(dir=folder)
        self.counts: list[int] = []

    def append(self, xyz: np.ndarray, inverse_distance: np.ndarray) -> None:
        xyz = np.ascontiguousarray(xyz, dtype=np.float32).reshape(-1, 3)
        inverse_distance = np.ascontiguousarray(inverse_distance, dtype=np.float32).reshape(-1)
        self._xyz.write(xyz.tobytes())
        self._inverse_distance.write(inverse_distance.tobytes())
        self.counts.append(len(inverse_distance))

    def frames(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """``(xyz, inverse_distance)`` of each appended frame, in order."""
        self._xyz.flush()
        self._inverse_distance.flush()
        self._xyz.seek(0)
        self._inverse_distance.seek(0)
        for count in self.counts:
            xyz = np.frombuffer(self._xyz.read(12 * count), dtype=np.float32).reshape(count, 3)
            yield xyz, np.frombuffer(self._inverse_distance.read(4 * count), dtype=np.float32)

    def close(self) -> None:
        self._xyz.close()
        self._inverse_distance.close()


#: Frames of landmarks per ``send_columns`` call when a run view finishes (bounds the memory
#: of the final 3D content: ~1 M landmark rows over the 60 s spiral at 640x480).
SEND_FRAMES = 100


def scale_unobservable(diag: FrameDiagnostics) -> float | None:
    """1 where Λ_scaledrift found no scale information in the window
    (:attr:`FrameDiagnostics.no_scale_information`), 0 where Λ is defined, None where neither
    (not computed, fewer than 3 keyframes, numerical reasons)."""
    if diag.scale_drift_indicator is not None:
        return 0.0
    return 1.0 if diag.no_scale_information else None


class RunView:
    """Builds the recording of one run (entity layout: :mod:`granite.visualization.rerun_logger`)."""

    def __init__(self, name: str, calibration, ground_truth: Trajectory | None,
                 rrd_path: str | Path | None = None, spawn: bool = False, d_max: float = 1.0,
                 scale_delta: float = 1.0):
        start = time.perf_counter()
        #: wall time spent logging: once when the recording is opened (blueprint), and per
        #: frame plus the final 3D content (what ``bench_vo.py --rerun`` reports).
        self.startup_seconds = 0.0
        self.seconds = 0.0
        self.log = RerunLogger(name, rrd_path, spawn)
        self.d_max = d_max
        self.scale_delta = scale_delta
        if calibration is not None:
            i = calibration.intrinsics
            self.log.log_camera_model(i["fx"], i["fy"], i["cx"], i["cy"], calibration.width, calibration.height)
        self.ground_truth = ground_truth
        if ground_truth is not None:
            self.log.log_trajectory("world/groundtruth", ground_truth.positions, GROUNDTRUTH_COLOR)
        #: (frame index, timestamp, window keyframe ids) of every logged frame; its landmarks
        #: are in ``self._landmarks``
        self._frames: list[tuple[int, float, tuple[int, ...]]] = []
        # beside the recording (a folder already checked writable), else in the system's
        self._landmarks = LandmarkSpool(None if rrd_path is None else Path(rrd_path).parent)
        self.startup_seconds = time.perf_counter() - start

    def log_frame(self, record: FrameRecord, image: np.ndarray | None, diag: FrameDiagnostics,
                  source: str | Path | None = None) -> None:
        """One processed frame; ``source``: the image file (logged as is when PNG / JPEG)."""
        start = time.perf_counter()
        log = self.log
        log.set_frame(record.index, record.timestamp)
        if image is not None:
            log.log_image(image, source)
        if len(record.track_ids):
            log.log_tracks(record.track_uv, record.track_level, record.track_inverse_distance, self.d_max)
        log.log_scalar("tracked_points", diag.tracked_points)
        log.log_scalar("finite_landmarks", diag.finite_landmarks)
        log.log_scalar("infinite_landmarks", diag.infinite_landmarks)
        log.log_scalar("keyframe", float(diag.keyframe))
        log.log_scalar("submap", diag.submap)
        if diag.negative_entropy is not None:
            log.log_scalar("negative_entropy", diag.negative_entropy)
        lam = getattr(diag, "scale_drift_indicator", None)
        if lam is not None and lam > 0:
            log.log_scalar("scale_drift_indicator", lam)
            log.log_scalar("log10_scale_drift_indicator", float(np.log10(lam)))
        lam_ref = getattr(diag, "scale_drift_indicator_ref", None)
        if lam_ref is not None:
            log.log_scalar("scale_drift_indicator_ref", lam_ref)
        unobservable = scale_unobservable(diag)
        if unobservable is not None:
            log.log_scalar("scale_unobservable", unobservable)
        self._frames.append((record.index, record.timestamp, tuple(record.keyframe_ids)))
        self._landmarks.append(record.landmarks_w, record.landmarks_inverse_distance)
        self.seconds += time.perf_counter() - start

    def finish(self, trajectory: Trajectory) -> None:
        """Log the aligned 3D content of every frame, then flush."""
        start = time.perf_counter()
        sims = similarity_per_submap(trajectory, self.ground_truth)
        sub = trajectory.submap if trajectory.submap is not None else np.zeros(len(trajectory), np.int64)
        row = {float(t): k for k, t in enumerate(trajectory.timestamps)}
        positions = np.full((len(trajectory), 3), np.nan)
        for k in range(len(trajectory)):
            if int(sub[k]) in sims:
                positions[k] = _apply(sims[int(sub[k])], trajectory.poses[k, :3, 3][None])[0]
        self.log.log_trajectory("world/estimate", positions, ESTIMATE_COLOR)
        index_row = {index: row.get(float(stamp)) for index, stamp, _ in self._frames}
        scale_error = self._scale_errors(trajectory, sims)
        finite = positions[np.all(np.isfinite(positions), axis=1)]
        extent = float(np.ptp(finite, axis=0).max()) if len(finite) else 1.0
        frustum_depth = max(0.02 * extent, 0.05)
        frames, stamps, cameras, keyframes = [], [], [], []
        chunk: tuple[list, list, list, list] = ([], [], [], [])  # frames, stamps, points, colours
        for (index, stamp, keyframe_ids), (xyz, inverse_distance) in zip(self._frames,
                                                                         self._landmarks.frames()):
            k = index_row[index]
            if k is None or int(sub[k]) not in sims:
                continue
            sim = sims[int(sub[k])]
            frames.append(index)
            stamps.append(stamp)
            cameras.append(_aligned_pose(sim, trajectory.poses[k]))
            kf_rows = [index_row.get(f) for f in keyframe_ids]
            keyframes.append(np.array([_aligned_pose(sim, trajectory.poses[r]) for r in kf_rows
                                       if r is not None and int(sub[r]) == int(sub[k])]).reshape(-1, 4, 4))
            chunk[0].append(index)
            chunk[1].append(stamp)
            chunk[2].append(_apply(sim, xyz) if len(xyz) else np.zeros((0, 3)))
            chunk[3].append(inverse_distance_colors(inverse_distance / sim[0], self.d_max))
            if len(chunk[0]) == SEND_FRAMES:
                self.log.send_points3d("world/landmarks", *chunk, radius=0.04)
                chunk = ([], [], [], [])
            if float(stamp) in scale_error:
                self.log.add_scalar("relative_scale_error", index,
                                    self.log.elapsed(stamp), scale_error[float(stamp)])
        self.log.send_points3d("world/landmarks", *chunk, radius=0.04)
        self.log.send_camera_poses(frames, stamps, np.array(cameras).reshape(-1, 4, 4))
        self.log.send_keyframes(frames, stamps, keyframes, frustum_depth)
        self._landmarks.close()
        self.log.close()
        self.seconds += time.perf_counter() - start

    def discard(self) -> None:
        """Give up the recording after an error: no file is written."""
        self._landmarks.close()
        self.log.discard()

    def _scale_errors(self, trajectory: Trajectory, sims: dict) -> dict[float, float]:
        """Relative scale error per estimate timestamp (empty without ground truth)."""
        if self.ground_truth is None or not sims:
            return {}
        try:
            series = relative_scale_error(trajectory, self.ground_truth, self.scale_delta,
                                          {k: v[0] for k, v in sims.items()})
        except (GraniteError, ValueError):
            return {}
        return {float(t): float(e) for t, e in zip(series.timestamps, series.errors)}
