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
        # per new landmark: the frames that saw it and the one with the longest baseline (the
        # first of equals), triangulated together per frame
        keep = np.flatnonzero(valid)
        seen_by = []
        by_frame: dict[int, list[int]] = {}
        for j in keep.tolist():
            tid = new_ids[j]
            seen = [f for f in frames if tid in tracks[f].positions]
            seen_by.append(seen)
            if triangulate:
                best = None
                for f in seen:
                    if baselines[f] >= self.min_baseline and (best is None or baselines[f] > baselines[best]):
                        best = f
                if best is not None:
                    by_frame.setdefault(best, []).append(j)
        inv_dist = np.zeros(len(new_ids))
        for f, rows in by_frame.items():
            uv_f = np.array([tracks[f].positions[new_ids[j]] for j in rows])
            inv_dist[rows] = self.inverse_distances(T_w_h, bearings[rows], f, uv_f)
        ids = [new_ids[j] for j in keep.tolist()]
        for j, tid in zip(keep.tolist(), ids):
            win.add_landmark(tid, host, bearings[j], float(inv_dist[j]))
        # the observations one frame at a time (host first, then the frames in window order:
        # each landmark's observations keep that order, which the packing follows)
        seen_in = {f: [] for f in frames}
        for tid, seen in zip(ids, seen_by):
            for f in seen:
                seen_in[f].append(tid)
        for f, in_f in [(host, ids), *seen_in.items()]:
            if in_f:
                ft = tracks[f]
                win.add_observations(f, in_f, np.array([ft.positions[t] for t in in_f]),
                                     [ft.levels[t] for t in in_f])
        return len(keep)

    def observe_hosted_by(self, host: int, frame_id: int, frame_tracks: FrameTracks) -> None:
        """Observations in ``frame_id`` of the landmarks a keyframe hosts that it tracks but does
        not observe yet (the current frame sees the landmarks of the previous frame made
        keyframe)."""
        win, db = self.window, self.window.landmarks
        for tid in db.hosted_by(host):
            if not db.has_observation(tid, frame_id) and tid in frame_tracks.positions:
                win.add_observation(tid, frame_id, frame_tracks.positions[tid],
                                    frame_tracks.levels[tid])

    def inverse_distances(self, T_w_h: np.ndarray, bearings_h: np.ndarray, frame: int,
                          uv: np.ndarray) -> np.ndarray:
        """Inverse distances (n,) of host bearings (n, 3) (host pose ``T_w_h``) from one more
        observation each, at pixels ``uv`` (n, 2) in the window frame ``frame``: two-view
        triangulation of all of them at once; 0 where it fails (pixel not unprojectable,
        rays parallel or not in front of both cameras)."""
        b_t, ok = self.bearings(uv)
        T_t_h = se3_inverse(self.window.pose(frame)) @ T_w_h
        points, valid = triangulate_bearings(T_t_h[:3, :3], T_t_h[:3, 3], bearings_h, b_t)
        distance = np.linalg.norm(points, axis=1)
        good = ok & valid & (distance > 0.0)
        return np.where(good, 1.0 / np.where(good, distance, 1.0), 0.0)

    def retriangulate_infinite(self, frame_id: int) -> None:
        """Every new observation of a d = 0 landmark with enough baseline to its host triggers a
        triangulation attempt (IV-B); the attempts of the landmarks of one host run together."""
        win = self.window
        db = win.landmarks
        T_w_c = win.pose(frame_id)
        ids = np.fromiter(db.observed_in(frame_id), dtype=np.int64)
        _, inv, hosts = db.states_of(ids)
        pick = ~(inv > 0.0) & (hosts != frame_id)
        by_host: dict[int, list[int]] = {}
        for lm_id, host in zip(ids[pick].tolist(), hosts[pick].tolist()):
            by_host.setdefault(host, []).append(lm_id)
        for host, lm_ids in by_host.items():
            T_w_h = win.pose(host)
            if np.linalg.norm(T_w_c[:3, 3] - T_w_h[:3, 3]) < self.min_baseline:
                continue
            bearings = np.array([db.landmark(i).bearing for i in lm_ids])
            uv = np.array([db.observation(i, frame_id).uv for i in lm_ids])
            for lm_id, d in zip(lm_ids, self.inverse_distances(T_w_h, bearings, frame_id, uv).tolist()):
                win.set_inverse_distance(lm_id, d)
