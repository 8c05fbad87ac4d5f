"""The monocular VO of the paper (Fig. 2b), one frame at a time.

Per frame: KLT tracks from the frontend -> observations of known landmarks -> map
initialisation while fewer than ``min_finite_observations`` finite landmarks are seen
(Sec. IV-C) -> sliding-window Gauss-Newton -> negative-entropy keyframe decision (Sec. IV-D; the
*previous* frame becomes the keyframe and hosts new landmarks) -> re-triangulation of points at
infinity -> failure check (restart, new sub-map) -> outlier removal and marginalisation.

Before a map exists every landmark is at infinity (d = 0), so the VO tracks rotation only; the
translation of keyframes linked only by such points is tied by the backend's small prior
(Sec. IV-B). Every output pose ``T_w_c`` carries its sub-map index; a new sub-map starts at the
identity after a tracking failure and after a re-initialisation (a new, unrelated scale).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from granite.backend import SlidingWindow
from granite.backend.landmarks import bearings_from_stereo
from granite.estimator.config import VoConfig
from granite.estimator.diagnostics import FrameDiagnostics
from granite.estimator.initialization import initialize_two_view
from granite.estimator.keyframes import EntropyKeyframeSelector
from granite.estimator.triangulation import triangulate_bearings
from granite.estimator.window_policy import frames_to_marginalize
from granite.geometry import se3_exp, se3_inverse, se3_log
from granite.optical_flow import FrameToFrameOpticalFlow, OpticalFlowResult
from granite.optical_flow.prediction import predict_positions


#: Finite landmarks a frame must see to update the scene distance kept for re-initialisation.
_SCENE_MIN_POINTS = 20


@dataclass
class _Tracks:
    """The frontend's tracks of one window frame, indexed by track id."""

    positions: dict[int, np.ndarray]
    levels: dict[int, int]


@dataclass(frozen=True)
class FrameOutput:
    """What the VO publishes per frame."""

    T_w_c: np.ndarray
    diagnostics: FrameDiagnostics
    tracks: OpticalFlowResult | None
    #: inverse distance per track (NaN: no landmark, 0: at infinity), aligned with ``tracks``.
    track_inverse_distance: np.ndarray
    keyframe_ids: tuple[int, ...]
    #: finite landmarks of the window in world coordinates (M, 3) and their inverse distances
    #: (M,), filled only when :attr:`MonocularVO.export_landmarks` is set.
    landmarks_w: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    landmarks_inverse_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))


class MonocularVO:
    """Stateful monocular odometry. Feed frames in time order with :meth:`process`."""

    def __init__(self, camera, config: VoConfig | None = None):
        self.camera = camera
        self.config = config or VoConfig()
        est = self.config.estimator
        self.flow = FrameToFrameOpticalFlow(self.config.optical_flow, (camera.width, camera.height))
        self.window = SlidingWindow(camera, self.config.backend)
        self.selector = EntropyKeyframeSelector(
            est.keyframe_entropy_fraction, est.keyframe_min_connected, est.min_frames_after_keyframe
        )
        self.submap = 0
        self._tracks: dict[int, _Tracks] = {}
        self._last_pose = np.eye(4)
        self._motion: tuple[np.ndarray, float] | None = None  # (T_prev_last, dt) of the last step
        self._last_time = 0.0
        self._map_initialized = False
        #: mean distance (map units) of the finite landmarks seen in the last frame that saw at
        #: least ``_SCENE_MIN_POINTS`` of them: the scale a re-initialisation carries over.
        self._scene_distance: float | None = None
        self._previous_frame: int | None = None
        self.keyframe_log: list[tuple[int, int]] = []  # (frame id, sub-map) of every keyframe
        self.export_landmarks = False  # fill FrameOutput.landmarks_w (costs ~1 ms per frame)

    # ----------------------------------------------------------------------------- helpers
    def _bearings(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.camera.unproject(np.asarray(uv, dtype=np.float64).reshape(-1, 2))

    def _restart(self) -> None:
        """Forget the window and start an empty sub-map (the next frame starts it)."""
        self.window.reset()
        self._tracks.clear()
        self.selector.reset()
        self._map_initialized = False
        self._scene_distance = None
        self._previous_frame = None
        self.submap += 1
        self._last_pose = np.eye(4)
        self._motion = None

    def _landmark_points(self, landmark_ids, T_x_w: np.ndarray | None = None) -> np.ndarray:
        """Points (n, 3) of the given landmarks (all with d > 0) in frame x (``T_x_w``; the
        world without it), vectorised over landmarks and grouped by host keyframe."""
        db, win = self.window.landmarks, self.window
        lms = [db.landmark(int(i)) for i in landmark_ids]
        if not lms:
            return np.zeros((0, 3))
        s = np.array([lm.s for lm in lms], dtype=np.float64).reshape(-1, 2)
        d = np.array([lm.inv_dist for lm in lms])
        hosts = np.array([lm.host_frame_id for lm in lms])
        p_h = bearings_from_stereo(s) / d[:, None]
        out = np.empty_like(p_h)
        for host in np.unique(hosts):
            mask = hosts == host
            T = win.pose(int(host)) if T_x_w is None else T_x_w @ win.pose(int(host))
            out[mask] = p_h[mask] @ T[:3, :3].T + T[:3, 3]
        return out

    def window_landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite landmarks of the window: world points (M, 3) and inverse distances (M,)."""
        db = self.window.landmarks
        ids = [i for host in self.window.keyframe_ids for i in sorted(db.hosted_by(host))]
        inv = db.inverse_distances(ids)
        finite = [i for i, d in zip(ids, inv) if d > 0.0]
        return self._landmark_points(finite), inv[inv > 0.0]

    def _predict_pose(self, timestamp: float) -> np.ndarray:
        """Initial guess ``T_w_c`` for a new frame: constant velocity (the last relative motion,
        scaled to the elapsed time, so frame drops are extrapolated), or the last pose."""
        if not self.config.estimator.constant_velocity or self._motion is None:
            return self._last_pose
        T_prev_last, dt = self._motion
        if dt <= 0:
            return self._last_pose
        ratio = min((timestamp - self._last_time) / dt, 5.0)
        return self._last_pose @ se3_exp(ratio * se3_log(T_prev_last))

    def _predicted_track_positions(self, timestamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Where the frontend's current tracks should appear at ``timestamp`` under the
        constant-velocity pose: tracks of landmarks with d > 0 by their depth, the others by
        the infinite homography. None when there is no motion estimate yet."""
        if not self.config.estimator.motion_guided_tracking or self._motion is None:
            return None
        ids, uv = self.flow.current_tracks()
        if not len(ids):
            return None
        T_w_old = self._last_pose
        T_old_w = se3_inverse(T_w_old)
        T_new_old = se3_inverse(self._predict_pose(timestamp)) @ T_w_old
        inv = self.window.landmarks.inverse_distances(ids)
        depths = np.full(len(ids), np.nan)
        finite = np.flatnonzero(inv > 0.0)
        depths[finite] = self._landmark_points(ids[finite], T_old_w)[:, 2]
        uv_new, valid = predict_positions(uv, self.camera, T_new_old, depths)
        return ids[valid], uv_new[valid]

    def _connected(self, frame_id: int) -> tuple[int, int]:
        return self.window.num_connected(frame_id)

    def _add_landmarks_hosted_by(self, host: int) -> int:
        """Triangulate landmarks for the host keyframe's tracks that are not landmarks yet.

        Each uses the window frame that saw the track with the longest baseline; below
        ``min_triangulation_distance`` (or when triangulation fails) it goes in at infinity.
        Returns the number of landmarks added.
        """
        win, db = self.window, self.window.landmarks
        host_tracks = self._tracks[host]
        new_ids = [tid for tid in host_tracks.positions if tid not in db]
        if not new_ids:
            return 0
        uv = np.array([host_tracks.positions[t] for t in new_ids])
        bearings, valid = self._bearings(uv)
        T_w_h = win.pose(host)
        min_baseline = self.config.estimator.min_triangulation_distance
        frames = [f for f in win.frame_ids if f != host and f in self._tracks]
        baselines = {f: float(np.linalg.norm(win.pose(f)[:3, 3] - T_w_h[:3, 3])) for f in frames}
        added = 0
        for tid, b, ok in zip(new_ids, bearings, valid):
            if not ok:
                continue
            seen = [f for f in frames if tid in self._tracks[f].positions]
            inv_dist = 0.0
            candidates = sorted((f for f in seen if baselines[f] >= min_baseline), key=lambda f: -baselines[f])
            for f in candidates[:1]:
                inv_dist = self._triangulate_inverse_distance(T_w_h, b, f, self._tracks[f].positions[tid])
            win.add_landmark(tid, host, b, inv_dist)
            win.add_observation(tid, host, host_tracks.positions[tid], host_tracks.levels[tid])
            for f in seen:
                win.add_observation(tid, f, self._tracks[f].positions[tid], self._tracks[f].levels[tid])
            added += 1
        return added

    def _triangulate_inverse_distance(self, T_w_h: np.ndarray, bearing_h: np.ndarray, frame: int, uv) -> float:
        """Inverse distance of a host bearing from one more observation; 0 when it fails."""
        b_t, ok = self._bearings(uv)
        if not ok[0]:
            return 0.0
        T_t_h = se3_inverse(self.window.pose(frame)) @ T_w_h
        points, valid = triangulate_bearings(T_t_h[:3, :3], T_t_h[:3, 3], bearing_h[None], b_t)
        if not valid[0]:
            return 0.0
        distance = float(np.linalg.norm(points[0]))
        return 1.0 / distance if distance > 0 else 0.0

    def _retriangulate_infinite(self, frame_id: int) -> None:
        """Every new observation of a d = 0 landmark triggers a triangulation attempt (IV-B)."""
        db = self.window.landmarks
        T_w_c = self.window.pose(frame_id)
        min_baseline = self.config.estimator.min_triangulation_distance
        for lm_id in list(db.observed_in(frame_id)):
            lm = db.landmark(lm_id)
            if lm.inv_dist > 0.0 or lm.host_frame_id == frame_id:
                continue
            T_w_h = self.window.pose(lm.host_frame_id)
            if np.linalg.norm(T_w_c[:3, 3] - T_w_h[:3, 3]) < min_baseline:
                continue
            uv = db.observation(lm_id, frame_id).uv
            lm.inv_dist = min(
                self._triangulate_inverse_distance(T_w_h, lm.bearing, frame_id, uv),
                self.config.backend.max_inv_dist,
            )

    def _try_initialization(self, frame_id: int) -> bool:
        """Relative-pose map initialisation against every keyframe of the window (IV-C)."""
        cur = self._tracks[frame_id]
        focal = float(np.mean(self.camera.params[:2]))
        for kf in self.window.keyframe_ids:
            if kf == frame_id:
                continue
            ref = self._tracks[kf]
            common = [t for t in cur.positions if t in ref.positions]
            if len(common) < self.config.initialization.min_inliers:
                continue
            b_k, ok_k = self._bearings(np.array([ref.positions[t] for t in common]))
            b_c, ok_c = self._bearings(np.array([cur.positions[t] for t in common]))
            ok = ok_k & ok_c
            result = initialize_two_view(b_k[ok], b_c[ok], focal, self.config.initialization)
            if not result.success:
                continue
            ids = np.array(common)[ok]
            self._rebuild_window_after_initialization(kf, frame_id, result, ids)
            return True
        return False

    def _rebuild_window_after_initialization(self, kf: int, frame_id: int, result, ids) -> None:
        """Start the map from keyframe ``kf`` and the current frame: both become keyframes,
        inlier tracks become landmarks hosted by ``kf``, the prior is reset to the gauge of
        ``kf`` and the scale-fix term of Eq. 9 fixes their distance."""
        T_w_k = self.window.pose(kf)
        scale = 1.0
        if self._map_initialized:  # the map was lost (e.g. all points at infinity after a turn)
            if self.config.estimator.reinit_keeps_scale and self._scene_distance:
                # Same sub-map: choose the new scale so the scene keeps its mean distance.
                inliers = result.points_k[: len(ids)][result.inliers[: len(ids)]]
                scale = self._scene_distance / float(np.mean(np.linalg.norm(inliers, axis=1)))
            else:  # an unrelated scale: a new sub-map
                self.submap += 1
        T_c_k = np.eye(4)
        T_c_k[:3, :3], T_c_k[:3, 3] = result.R_c_k, scale * result.t_c_k
        T_w_c = T_w_k @ se3_inverse(T_c_k)
        tracks_k, tracks_c = self._tracks[kf], self._tracks[frame_id]
        self.window.reset()
        self._tracks = {kf: tracks_k, frame_id: tracks_c}
        self.window.add_frame(kf, T_w_k, is_keyframe=True)
        self.window.add_frame(frame_id, T_w_c, is_keyframe=True)
        for tid, point, inlier in zip(ids, result.points_k[: len(ids)], result.inliers[: len(ids)]):
            if not inlier:
                continue
            distance = scale * float(np.linalg.norm(point))
            tid = int(tid)
            self.window.add_landmark(tid, kf, point / distance, 1.0 / distance)
            self.window.add_observation(tid, kf, tracks_k.positions[tid], tracks_k.levels[tid])
            self.window.add_observation(tid, frame_id, tracks_c.positions[tid], tracks_c.levels[tid])
        self.window.set_scale_fix(kf, frame_id, float(np.linalg.norm(T_c_k[:3, 3])))
        self._add_landmarks_hosted_by(kf)  # outlier tracks of kf: at infinity or triangulated
        self._map_initialized = True
        self.keyframe_log.append((frame_id, self.submap))
        self.selector.reset()

    def _optimize_and_select_keyframe(self, frame_id: int) -> tuple[float | None, bool]:
        """Gauss-Newton on the window, then the keyframe decision of Sec. IV-D (taken on the
        system linearised after ``entropy_iteration`` iterations), re-triangulation of points
        at infinity and outlier removal. Returns (negative entropy, keyframe inserted)."""
        win, est = self.window, self.config.estimator
        report = win.optimize(snapshot_iteration=est.entropy_iteration - 1)
        finite, infinite = self._connected(frame_id)
        negative_entropy = None
        if report.snapshot is not None and frame_id in report.snapshot.frame_ids:
            negative_entropy = report.snapshot.negative_entropy(frame_id, include_translation=finite > 5)
        take = self.selector.update(
            negative_entropy if negative_entropy is not None else float("nan"), finite + infinite
        )
        inserted = False
        if take and not win.is_keyframe(frame_id):
            kf = frame_id
            prev = self._previous_frame
            if est.previous_frame_as_keyframe and prev is not None and prev in win and not win.is_keyframe(prev):
                kf = prev
            win.make_keyframe(kf)
            self._add_landmarks_hosted_by(kf)
            if kf != frame_id:  # the current frame observes the new landmarks too
                db, cur = win.landmarks, self._tracks[frame_id]
                for tid in db.hosted_by(kf):
                    if not db.has_observation(tid, frame_id) and tid in cur.positions:
                        win.add_observation(tid, frame_id, cur.positions[tid], cur.levels[tid])
            self.keyframe_log.append((kf, self.submap))
            self.selector.reset()
            inserted = True
            if est.keyframe_extra_iterations:
                win.optimize(max_iterations=est.keyframe_extra_iterations)
        self._retriangulate_infinite(frame_id)
        win.remove_outliers()
        return negative_entropy, inserted

    # ----------------------------------------------------------------------------- main
    def process(self, frame_id: int, timestamp: float, image: np.ndarray | None) -> FrameOutput:
        """Process one frame; ``image`` None marks a missing or corrupt image (skipped)."""
        start = time.perf_counter()
        est = self.config.estimator
        if image is None:
            diag = FrameDiagnostics(timestamp, frame_id, self.submap, "skipped")
            return FrameOutput(self._last_pose.copy(), diag, None, np.zeros(0), tuple(self.window.keyframe_ids))

        tracks = self.flow.process(timestamp, image, predicted=self._predicted_track_positions(timestamp))
        if tracks.rejected is not None:  # blank / wrong size: the frontend kept its last frame
            diag = FrameDiagnostics(timestamp, frame_id, self.submap, "skipped",
                                    processing_ms=(time.perf_counter() - start) * 1e3)
            return FrameOutput(self._last_pose.copy(), diag, tracks, np.zeros(0), tuple(self.window.keyframe_ids))
        self._tracks[frame_id] = _Tracks(
            {int(t): p for t, p in zip(tracks.ids, tracks.positions)},
            {int(t): int(c) for t, c in zip(tracks.ids, tracks.levels)},
        )
        win = self.window
        first_of_submap = not win.frame_ids
        guess = np.eye(4) if first_of_submap else self._predict_pose(timestamp)
        win.add_frame(frame_id, guess, is_keyframe=first_of_submap)
        keyframe_taken = False
        if first_of_submap:
            self._add_landmarks_hosted_by(frame_id)  # all at infinity: no other frame yet
            self.keyframe_log.append((frame_id, self.submap))
            keyframe_taken = True
        else:
            win.add_observations(frame_id, tracks.ids, tracks.positions, tracks.levels, skip_unknown=True)

        finite, _ = self._connected(frame_id)
        reinitialized = False
        if not first_of_submap and finite < est.min_finite_observations:
            had_map = self._map_initialized
            reinitialized = self._try_initialization(frame_id) and had_map

        negative_entropy, diverged = None, False
        if len(win.frame_ids) > 1:
            try:
                negative_entropy, inserted = self._optimize_and_select_keyframe(frame_id)
                keyframe_taken |= inserted
            except (FloatingPointError, np.linalg.LinAlgError):
                diverged = True  # treated as a tracking failure below

        finite, infinite = self._connected(frame_id)
        state = ("reinit" if reinitialized else "tracking") if self._map_initialized else "init"
        T_w_c = win.pose(frame_id)
        submap = self.submap
        if diverged or (len(win.keyframe_ids) >= 2 and finite + infinite < est.failure_min_connected):
            state = "lost"
            self._restart()
        else:
            marg = frames_to_marginalize(win, self.config.backend)
            if marg:
                win.marginalize(marg)
                for f in marg:
                    self._tracks.pop(f, None)
            if self._previous_frame is not None and self._map_initialized:
                self._motion = (se3_inverse(self._last_pose) @ T_w_c, timestamp - self._last_time)
            self._last_pose, self._last_time = T_w_c, timestamp
            self._previous_frame = frame_id

        inv = win.landmarks.inverse_distances(tracks.ids)
        if state in ("tracking", "reinit"):
            seen = inv[inv > 0.0]
            if len(seen) >= _SCENE_MIN_POINTS:
                self._scene_distance = float(np.mean(1.0 / seen))
        diag = FrameDiagnostics(
            timestamp, frame_id, submap, state, len(tracks), finite, infinite, keyframe_taken,
            negative_entropy if negative_entropy is not None and np.isfinite(negative_entropy) else None,
            (time.perf_counter() - start) * 1e3,
        )
        if self.export_landmarks:
            points, inv_dist = self.window_landmarks()
            return FrameOutput(T_w_c, diag, tracks, inv, tuple(win.keyframe_ids), points, inv_dist)
        return FrameOutput(T_w_c, diag, tracks, inv, tuple(win.keyframe_ids))
