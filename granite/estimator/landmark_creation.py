"""New landmarks for a keyframe's tracks, and re-triangulation of points at infinity (IV-B).

A new landmark is hosted by a keyframe: its bearing is the track's unprojection in the host,
its inverse distance comes from triangulating with the window frame that saw the track with
the longest baseline. Below ``min_triangulation_distance`` (map units), or when triangulation
fails, it goes in at infinity (``d = 0``); every later observation of such a point with enough
baseline triggers a new triangulation attempt.
"""

from __future__ import annotations

import numpy as np

from granite.backend import SlidingWindow
from granite.estimator.tracks import FrameTracks
from granite.estimator.triangulation import triangulate_bearings
from granite.geometry import se3_inverse


class LandmarkTriangulator:
    """Creates and re-triangulates landmarks in ``window`` from frontend tracks."""

    def __init__(self, window: SlidingWindow, camera, min_triangulation_distance: float):
        self.window = window
        self.camera = camera
        self.min_baseline = min_triangulation_distance

    def bearings(self, uv) -> tuple[np.ndarray, np.ndarray]:
        """Unit bearings (n, 3) in the camera frame of pixels (n, 2), and validity (n,)."""
        return self.camera.unproject(np.asarray(uv, dtype=np.float64).reshape(-1, 2))

    def add_hosted_by(self, tracks: dict[int, FrameTracks], host: int, triangulate: bool = True) -> int:
        """Landmarks for the host keyframe's tracks that are not landmarks yet, observed in the
        host and in every window frame of ``tracks`` that saw them; all at infinity when
        ``triangulate`` is false. Returns the number added."""
        win, db = self.window, self.window.landmarks
        host_tracks = tracks[host]
        new_ids = [tid for tid in host_tracks.positions if tid not in db]
        if not new_ids:
            return 0
        uv = np.array([host_tracks.positions[t] for t in new_ids])
        bearings, valid = self.bearings(uv)
        T_w_h = win.pose(host)
        frames = [f for f in win.frame_ids if f != host and f in tracks]
        baselines = {f: float(np.linalg.norm(win.pose(f)[:3, 3] - T_w_h[:3, 3])) for f in frames}
        added = 0
        for tid, b, ok in zip(new_ids, bearings, valid):
            if not ok:
                continue
            seen = [f for f in frames if tid in tracks[f].positions]
            inv_dist = 0.0
            candidates = sorted((f for f in seen if baselines[f] >= self.min_baseline),
                                key=lambda f: -baselines[f]) if triangulate else []
            for f in candidates[:1]:
                inv_dist = self.inverse_distance(T_w_h, b, f, tracks[f].positions[tid])
            win.add_landmark(tid, host, b, inv_dist)
            win.add_observation(tid, host, host_tracks.positions[tid], host_tracks.levels[tid])
            for f in seen:
                win.add_observation(tid, f, tracks[f].positions[tid], tracks[f].levels[tid])
            added += 1
        return added

    def observe_hosted_by(self, host: int, frame_id: int, frame_tracks: FrameTracks) -> None:
        """Observations in ``frame_id`` of the landmarks a keyframe hosts that it tracks but does
        not observe yet (the current frame sees the landmarks of the previous frame made
        keyframe)."""
        win, db = self.window, self.window.landmarks
        for tid in db.hosted_by(host):
            if not db.has_observation(tid, frame_id) and tid in frame_tracks.positions:
                win.add_observation(tid, frame_id, frame_tracks.positions[tid],
                                    frame_tracks.levels[tid])

    def inverse_distance(self, T_w_h: np.ndarray, bearing_h: np.ndarray, frame: int,
                         uv) -> float:
        """Inverse distance of a host bearing from one more observation at pixel ``uv`` in a
        window frame; 0 when it fails."""
        b_t, ok = self.bearings(uv)
        if not ok[0]:
            return 0.0
        T_t_h = se3_inverse(self.window.pose(frame)) @ T_w_h
        points, valid = triangulate_bearings(T_t_h[:3, :3], T_t_h[:3, 3], bearing_h[None], b_t)
        if not valid[0]:
            return 0.0
        distance = float(np.linalg.norm(points[0]))
        return 1.0 / distance if distance > 0 else 0.0

    def retriangulate_infinite(self, frame_id: int) -> None:
        """Every new observation of a d = 0 landmark with enough baseline to its host triggers a
        triangulation attempt (IV-B)."""
        win = self.window
        db = win.landmarks
        T_w_c = win.pose(frame_id)
        ids = np.fromiter(db.observed_in(frame_id), dtype=np.int64)
        _, inv, hosts = db.states_of(ids)
        for lm_id in ids[~(inv > 0.0) & (hosts != frame_id)].tolist():
            lm = db.landmark(lm_id)
            T_w_h = win.pose(lm.host_frame_id)
            if np.linalg.norm(T_w_c[:3, 3] - T_w_h[:3, 3]) < self.min_baseline:
                continue
            uv = db.observation(lm_id, frame_id).uv
            win.set_inverse_distance(lm_id, self.inverse_distance(T_w_h, lm.bearing, frame_id, uv))
