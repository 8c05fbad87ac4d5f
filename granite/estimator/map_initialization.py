"""Map initialisation from two views (paper Sec. IV-C), at the level of the window.

:func:`find_map_initialization` tries the relative-pose initialisation
(:func:`granite.estimator.initialization.initialize_two_view`) of the current frame against every
keyframe of the window; :func:`build_initial_map` restarts the window from the two views: both
become keyframes, the inlier tracks become finite landmarks hosted by the keyframe, the prior is
reset to the keyframe's gauge and the scale fix of Eq. 9 fixes the distance of the two views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from granite.backend import SlidingWindow
from granite.estimator.initialization import (
    InitializationConfig,
    InitializationResult,
    initialize_two_view,
)
from granite.estimator.landmark_creation import LandmarkTriangulator
from granite.estimator.tracks import FrameTracks
from granite.geometry import se3_inverse


@dataclass(frozen=True)
class MapInitialization:
    """An accepted two-view initialisation between keyframe ``keyframe`` and frame ``frame``:
    ``result.R_c_k, t_c_k`` map points of the keyframe into the frame (``|t_c_k|`` follows from
    ``mean_distance``); ``track_ids[i]`` is the track of ``result``'s correspondence ``i``."""

    keyframe: int
    frame: int
    result: InitializationResult
    track_ids: np.ndarray

    def inlier_points(self) -> np.ndarray:
        """Triangulated inlier points (n, 3) in the keyframe, at the result's scale."""
        n = len(self.track_ids)
        return self.result.points_k[:n][self.result.inliers[:n]]


def find_map_initialization(window: SlidingWindow, triangulator: LandmarkTriangulator,
                            tracks: dict[int, FrameTracks], frame_id: int,
                            config: InitializationConfig) -> MapInitialization | None:
    """The first keyframe of the window (ascending id) that initialises with ``frame_id``."""
    cur = tracks[frame_id]
    focal = float(np.mean(triangulator.camera.params[:2]))
    for kf in window.keyframe_ids:
        if kf == frame_id:
            continue
        ref = tracks[kf]
        common = [t for t in cur.positions if t in ref.positions]
        if len(common) < config.min_inliers:
            continue
        b_k, ok_k = triangulator.bearings(np.array([ref.positions[t] for t in common]))
        b_c, ok_c = triangulator.bearings(np.array([cur.positions[t] for t in common]))
        ok = ok_k & ok_c
        result = initialize_two_view(b_k[ok], b_c[ok], focal, config)
        if result.success:
            return MapInitialization(kf, frame_id, result, np.array(common)[ok])
    return None


def build_initial_map(window: SlidingWindow, triangulator: LandmarkTriangulator,
                      tracks: dict[int, FrameTracks], init: MapInitialization,
                      scale: float = 1.0) -> dict[int, FrameTracks]:
    """Restart ``window`` from the two views of ``init`` with its translation (and points)
    multiplied by ``scale``; the keyframe keeps its pose. The keyframe's other tracks become
    landmarks too (at infinity or triangulated). Returns the tracks of the new window's
    frames."""
    kf, frame_id, result, ids = init.keyframe, init.frame, init.result, init.track_ids
    T_w_k = window.pose(kf)
    T_c_k = np.eye(4)
    T_c_k[:3, :3], T_c_k[:3, 3] = result.R_c_k, scale * result.t_c_k
    T_w_c = T_w_k @ se3_inverse(T_c_k)
    tracks_k, tracks_c = tracks[kf], tracks[frame_id]
    window.reset()
    kept = {kf: tracks_k, frame_id: tracks_c}
    window.add_frame(kf, T_w_k, is_keyframe=True)
    window.add_frame(frame_id, T_w_c, is_keyframe=True)
    for tid, point, inlier in zip(ids, result.points_k[: len(ids)], result.inliers[: len(ids)]):
        if not inlier:
            continue
        distance = scale * float(np.linalg.norm(point))
        tid = int(tid)
        window.add_landmark(tid, kf, point / distance, 1.0 / distance)
        window.add_observation(tid, kf, tracks_k.positions[tid], tracks_k.levels[tid])
        window.add_observation(tid, frame_id, tracks_c.positions[tid], tracks_c.levels[tid])
    window.set_scale_fix(kf, frame_id, float(np.linalg.norm(T_c_k[:3, 3])))
    triangulator.add_hosted_by(kept, kf)  # outlier tracks of kf: at infinity or triangulated
    return kept
