"""The monocular VO of the paper (Fig. 2b), one frame at a time.

Per frame: KLT tracks from the frontend -> observations of known landmarks -> map
initialisation while fewer than ``min_finite_observations`` finite landmarks are seen
(Sec. IV-C, :mod:`granite.estimator.map_initialization`) -> sliding-window Gauss-Newton ->
negative-entropy keyframe decision (Sec. IV-D; the *previous* frame becomes the keyframe and hosts
new landmarks, :mod:`granite.estimator.landmark_creation`) -> re-triangulation of points at
infinity -> outlier removal (ours: then a few more iterations without the outliers when they
were a noticeable share of the frame's observations) -> failure check (restart, new sub-map) ->
marginalisation (:mod:`granite.estimator.window_policy`). The states and their transitions are in
:mod:`granite.estimator.tracking_state`.

Before a map exists every landmark is at infinity (d = 0), so the VO tracks rotation only; the
translation of keyframes linked only by such points is tied by the backend's small prior
(Sec. IV-B). Every output pose ``T_w_c`` carries its sub-map index. A tracking failure starts a
new sub-map at the identity with the lost frame. A mapped frame that observes few finite
landmarks first re-finds the window's others from their predicted positions
(:mod:`granite.estimator.recovery`). Map initialisation ranks the keyframes by the
rotation-compensated parallax of their shared tracks and, while no map exists, keeps the best
of them in the window (docs/estimator.md). A re-initialisation (the map lost, every point at infinity) keeps
the sub-map when ``reinit_keeps_scale`` is set (the default) and a scene distance is known: the
new map is scaled to it; otherwise it starts a new sub-map (the fixed initial scale, unrelated
to the old one) that continues from the current pose.
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field

import numpy as np

from granite.backend import OptimizeReport, ScaleDriftResult, SlidingWindow, WorkspacePool, scale_drift_task
from granite.estimator.config import VoConfig
from granite.estimator.diagnostics import FrameDiagnostics
from granite.estimator.keyframes import EntropyKeyframeSelector, depth_ratio_exceeds, median_depth
from granite.estimator.landmark_creation import LandmarkTriangulator
from granite.estimator.map_initialization import build_initial_map, find_map_initialization, init_candidates
from granite.estimator.motion_model import (ConstantVelocityModel, PredictionBasis, bearing_rotation,
                                            prediction_basis)
from granite.estimator.recovery import LandmarkRefinder
from granite.estimator.tracking_state import FrameStatus, MapState, next_state
from granite.estimator.tracks import FrameTracks
from granite.estimator.window_policy import frames_to_marginalize
from granite.optical_flow import FrameToFrameOpticalFlow, OpticalFlowResult

#: A tracking failure needs a map of at least two keyframes (the reference's monocular
#: ``min_keyframes``): before that, few connected points are the normal start of a sub-map.
_FAILURE_MIN_KEYFRAMES = 2


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
    #: Λ_scaledrift still being computed on another thread (:attr:`MonocularVO.scale_drift_executor`):
    #: the diagnostics' two indicator fields are filled by :meth:`MonocularVO.complete`
    scale_drift_pending: Future | None = field(default=None, repr=False, compare=False)


class MonocularVO:
    """Stateful monocular odometry. Feed frames in time order with :meth:`process`."""

    def __init__(self, camera, config: VoConfig | None = None):
        self.camera = camera
        self.config = config or VoConfig()
        est = self.config.estimator
        self.flow = FrameToFrameOpticalFlow(self.config.optical_flow, (camera.width, camera.height))
        self.window = SlidingWindow(camera, self.config.backend)
        self.triangulator = LandmarkTriangulator(self.window, camera, est.min_triangulation_distance)
        self.selector = EntropyKeyframeSelector(
            est.keyframe_entropy_fraction, est.keyframe_min_connected, est.min_frames_after_keyframe,
            est.keyframe_on_invalid_entropy,
        )
        self.refinder = LandmarkRefinder(self.window, camera, self.config.optical_flow,
                                         est.refind_fb_threshold_sq, est.refind_min_zncc)
        #: while no map exists: the keyframe with the most rotation-compensated parallax to the
        #: newest frame (kept in the window with ``init_keep_reference``)
        self._init_reference: int | None = None
        self.motion = ConstantVelocityModel(est.constant_velocity, est.max_velocity_extrapolation)
        self.state = MapState.EMPTY
        self.submap = 0
        self._tracks: dict[int, FrameTracks] = {}
        #: mean distance (map units) of the finite landmarks seen in the last frame that saw at
        #: least ``scene_distance_min_points`` of them: the scale a re-initialisation carries over.
        self._scene_distance: float | None = None
        self._previous_frame: int | None = None
        #: timestamps of the window's frames (the keyframe-age rule of the window policy)
        self._timestamps: dict[int, float] = {}
        #: what the next frame's predictions are made from (motion-guided tracking), fixed by
        #: :meth:`note_tracks` (``predict_before_estimate``) or inside :meth:`estimate`
        self._prediction_basis: PredictionBasis | None = None
        #: the last predictions handed to the frontend (ids, pixels)
        self._last_prediction: tuple[np.ndarray, np.ndarray] | None = None
        #: the rotation from the prediction basis's frame to the predicted frame that those
        #: predictions assumed (``tracked_rotation_guess`` only)
        self._last_prediction_rotation: np.ndarray | None = None
        #: (timestamp, T_w_c): the motion model's pose for the frame whose tracks
        #: :meth:`note_tracks` saw, with the rotation its tracks measured (``tracked_rotation_guess``)
        self._tracked_guess: tuple[float, np.ndarray] | None = None
        self.keyframe_log: list[tuple[int, int]] = []  # (frame id, sub-map) of every keyframe
        self.export_landmarks = False  # fill FrameOutput.landmarks_w (costs ~1 ms per frame)
        #: when set (the concurrent pipeline), Λ_scaledrift of a frame is computed there from a
        #: copy of the window, while the estimator goes on with the next frame; the frame's
        #: output is then finished by :meth:`complete`. None: computed in line (same values).
        self.scale_drift_executor: Executor | None = None
        self._scale_drift_workspaces = WorkspacePool()  # the buffers of those computations
        #: the frame's optimisation, for its diagnostics: iterations over every call, and
        #: whether the main call converged (None: it did not run)
        self._gn_iterations = 0
        self._gn_converged: bool | None = None

    # ----------------------------------------------------------------------------- outputs
    def window_landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite landmarks of the window: world points (M, 3) and inverse distances (M,)."""
        db = self.window.landmarks
        ids = db.ids_by_host(self.window.keyframe_ids)
        inv = db.inverse_distances(ids)
        return self.window.landmark_points(ids[inv > 0.0]), inv[inv > 0.0]

    def _skipped(self, timestamp: float, frame_id: int, tracks: OpticalFlowResult | None,
                 start: float | None) -> FrameOutput:
        ms = 0.0 if start is None else (time.perf_counter() - start) * 1e3
        diag = FrameDiagnostics(timestamp, frame_id, self.submap, FrameStatus.SKIPPED.value,
                                processing_ms=ms)
        return FrameOutput(self.motion.last_pose.copy(), diag, tracks, np.zeros(0),
                           tuple(self.window.keyframe_ids))

    # ------------------------------------------------------------------------------ steps
    def _restart(self) -> None:
        """Forget the window and start an empty sub-map (the next frame starts it)."""
        self.window.reset()
        self._tracks.clear()
        self._timestamps.clear()
        self.refinder.reset()
        self._init_reference = None
        self.selector.reset()
        self._scene_distance = None
        self._previous_frame = None
        self.submap += 1
        self.motion.reset()

    def _start_submap(self, frame_id: int, timestamp: float, tracks: OpticalFlowResult,
                      image: np.ndarray) -> np.ndarray:
        """After a restart the lost frame is the first frame of the new sub-map (the
        reference's behaviour): a keyframe at the identity whose tracks are landmarks at
        infinity. Returns its pose."""
        self._tracks[frame_id] = FrameTracks.from_result(tracks)
        self.window.add_frame(frame_id, np.eye(4), is_keyframe=True)
        self._timestamps[frame_id] = timestamp
        self.triangulator.add_hosted_by(self._tracks, frame_id)
        self.keyframe_log.append((frame_id, self.submap))
        if self.config.estimator.refind_enabled:
            self.refinder.add_image(frame_id, image)
        self.state = MapState.ROTATION_ONLY
        self.motion.update(np.eye(4), timestamp, measure_motion=False)
        self._previous_frame = frame_id
        return np.eye(4)

    def _try_initialization(self, frame_id: int) -> bool:
        """Relative-pose map initialisation against the window's keyframes (IV-C). A
        re-initialisation (the map was lost, e.g. all points at infinity after a turn) keeps
        the scene distance and the sub-map with ``reinit_keeps_scale``, otherwise starts a new
        sub-map at the initialisation's fixed scale."""
        est, cfg = self.config.estimator, self.config.initialization
        candidates = None
        if est.init_max_candidates > 0 or est.init_keep_reference:
            candidates = init_candidates(self.window, self.triangulator, self._tracks, frame_id,
                                         cfg.min_inliers)
            self._init_reference = candidates[0].keyframe if candidates else None
        init = find_map_initialization(self.window, self.triangulator, self._tracks, frame_id, cfg,
                                       est.init_max_candidates, est.init_candidate_min_parallax,
                                       candidates)
        if init is None:
            return False
        self._init_reference = None
        scale = 1.0
        if self.state is MapState.MAPPED:
            if self.config.estimator.reinit_keeps_scale and self._scene_distance:
                mean = float(np.mean(np.linalg.norm(init.inlier_points(), axis=1)))
                scale = self._scene_distance / mean
            else:
                self.submap += 1
        self._tracks = build_initial_map(self.window, self.triangulator, self._tracks, init,
                                         scale)
        self.keyframe_log.append((frame_id, self.submap))
        self.selector.reset()
        return True

    def _insert_keyframe(self, frame_id: int, forced: bool, triangulate: bool = True) -> bool:
        """Make the previous frame (paper IV-D; the current one for ablation ‡ or when there is
        none) a keyframe hosting new landmarks, then run the extra iterations. When the previous
        frame already is a keyframe, an entropy decision is dropped (its surviving tracks are
        landmarks already) and only a keyframe ``forced`` by too few connected points makes the
        current frame one. Returns whether a keyframe was inserted."""
        win, est = self.window, self.config.estimator
        kf = frame_id
        prev = self._previous_frame
        if est.previous_frame_as_keyframe and prev is not None and prev in win:
            if not win.is_keyframe(prev):
                kf = prev
            elif not forced:
                return False
        win.make_keyframe(kf)
        self.triangulator.add_hosted_by(self._tracks, kf, triangulate=triangulate)
        if kf != frame_id:  # the current frame observes the new landmarks too
            self.triangulator.observe_hosted_by(kf, frame_id, self._tracks[frame_id])
        self.keyframe_log.append((kf, self.submap))
        self.selector.reset()
        if est.keyframe_extra_iterations:
            self._optimize(max_iterations=est.keyframe_extra_iterations,
                           reuse_linearizations=False)
        return True

    def _scene_scale_changed(self, frame_id: int) -> bool:
        """The scene-scale keyframe criterion (``keyframe_depth_change``): the median depth of
        the frame's finite landmarks differs from the newest keyframe's by more than the
        factor ``1 + keyframe_depth_change``."""
        kfs = [k for k in self.window.keyframe_ids if k != frame_id]
        if not kfs:
            return False
        return depth_ratio_exceeds(median_depth(self.window, frame_id), median_depth(self.window, kfs[-1]),
                                   self.config.estimator.keyframe_depth_change)

    def _optimize_and_select_keyframe(self, frame_id: int) -> tuple[float | None, bool]:
        """Gauss-Newton on the window, then the keyframe decision of Sec. IV-D (taken on the
        system linearised after ``entropy_iteration`` iterations), re-triangulation of points
        at infinity, outlier removal and, when that took enough of the frame's observations,
        a few more iterations without them. Returns (negative entropy, keyframe inserted)."""
        win, est = self.window, self.config.estimator
        # the system linearised after ``entropy_iteration`` steps (0-based index of the loop)
        report = self._optimize(snapshot_iteration=est.entropy_iteration)
        self._gn_converged = report.converged
        finite, infinite = win.num_connected(frame_id)
        negative_entropy = None
        if report.snapshot is not None and frame_id in report.snapshot.frame_ids:
            negative_entropy = report.snapshot.negative_entropy(
                frame_id, include_translation=finite > est.entropy_translation_finite_points)
        take = self.selector.update(
            negative_entropy if negative_entropy is not None else float("nan"), finite + infinite
        )
        # the map measures this frame's translation only through finite landmarks (IV-C)
        measured = not est.triangulate_needs_map or finite >= est.min_finite_observations
        if (not take and est.keyframe_depth_change > 0.0 and finite >= est.min_finite_observations
                and self.selector.frames_since_keyframe > est.min_frames_after_keyframe):
            take = self._scene_scale_changed(frame_id)
        if (not take and est.keyframe_min_scale_links > 0 and finite >= est.min_finite_observations
                and len(win.keyframe_ids) >= 2 and self.selector.frames_since_keyframe > est.min_frames_after_keyframe):
            take = win.landmarks.num_scale_links(frame_id, win.keyframe_ids) < est.keyframe_min_scale_links
        inserted = take and not win.is_keyframe(frame_id) and self._insert_keyframe(
            frame_id, forced=finite + infinite < est.keyframe_min_connected, triangulate=measured)
        if measured:
            self.triangulator.retriangulate_infinite(frame_id)
        self._reoptimize_without_outliers(frame_id, win.remove_outliers())
        return negative_entropy, inserted

    def _reoptimize_without_outliers(self, frame_id: int, removed: list[tuple[int, int]]) -> None:
        """Optimise the window again for ``outlier_reoptimize_iterations`` when the outlier
        removal (``removed``: its ``(landmark, frame)`` pairs) took at least
        ``outlier_reoptimize_min_fraction`` of the frame's own observations: the frame's pose
        alone or the window (``outlier_reoptimize_states``)."""
        est, win = self.config.estimator, self.window
        removed_here = sum(1 for _, f in removed if f == frame_id)
        if not est.outlier_reoptimize_iterations or removed_here == 0 or frame_id not in win:
            return
        kept = sum(win.num_connected(frame_id))
        if removed_here < est.outlier_reoptimize_min_fraction * (kept + removed_here):
            return
        states = est.outlier_reoptimize_states
        if states != "window" and win.pose_refinable_alone(frame_id):
            self._gn_iterations += win.refine_pose(frame_id, est.outlier_reoptimize_iterations,
                                                   with_landmarks=states == "pose_and_landmarks").iterations
        else:
            self._optimize(max_iterations=est.outlier_reoptimize_iterations,
                           reuse_linearizations=False)

    def _optimize(self, **kwargs) -> OptimizeReport:
        """``window.optimize(**kwargs)``, its iterations counted for the frame's diagnostics."""
        report = self.window.optimize(**kwargs)
        self._gn_iterations += report.iterations
        return report

    def _initial_guess(self, timestamp: float) -> np.ndarray:
        """Where the optimisation of a frame starts: the motion model's pose, with the rotation
        the frame's tracks measured when :meth:`note_tracks` found one
        (``tracked_rotation_guess``)."""
        tracked = self._tracked_guess
        if tracked is not None and tracked[0] == timestamp:
            return tracked[1].copy()
        return self.motion.predict(timestamp)

    # ----------------------------------------------------------------------------- main
    def predict_tracks(self, timestamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The frontend's guesses for a frame at ``timestamp`` (motion-guided tracking): the
        only data that flows from the estimator back into the frontend, made from the basis
        (:class:`PredictionBasis`) fixed for the last frame: by :meth:`note_tracks` before its
        estimator step (``predict_before_estimate``, the default) or after its optimisation."""
        basis = self._prediction_basis
        self._last_prediction = None if basis is None else basis.predict(self.camera, timestamp)
        self._last_prediction_rotation = None
        if basis is not None and self.config.estimator.tracked_rotation_guess:
            self._last_prediction_rotation = basis.T_w_old[:3, :3].T @ basis.model.predict(timestamp)[:3, :3]
        return self._last_prediction

    @property
    def next_tracking_waits_for_estimate(self) -> bool:
        """Whether the next frame's predictions need this frame's optimisation (motion-guided
        tracking without ``predict_before_estimate``)."""
        est = self.config.estimator
        return est.motion_guided_tracking and not est.predict_before_estimate

    def note_tracks(self, timestamp: float, tracks: OpticalFlowResult) -> None:
        """A frame's tracks are known and it is not estimated yet; with
        ``predict_before_estimate`` the next frame's prediction basis is fixed here. Call it
        between the tracking and :meth:`estimate` of every frame."""
        est = self.config.estimator
        if not (est.motion_guided_tracking and est.predict_before_estimate) or tracks.rejected is not None:
            return
        model = self.motion
        self._tracked_guess = None
        if not model.has_motion:
            self._prediction_basis = None
            return
        T_w_c = model.predict(timestamp).copy()
        last = self._last_prediction
        if last is not None:
            _, i_p, i_t = np.intersect1d(last[0], tracks.ids, assume_unique=True, return_indices=True)
            R = bearing_rotation(self.camera, last[1][i_p], tracks.positions[i_t])
            if R is not None:
                prev = self._previous_frame
                if (est.tracked_rotation_guess and prev is not None and prev in self.window
                        and self._last_prediction_rotation is not None):
                    # the tracks' rotation from the previous frame, on its current estimate
                    guess = T_w_c.copy()
                    # projected onto SO(3): the guess feeds the window pose, which feeds the motion
                    # model's extrapolation, which feeds the next guess, and that loop amplifies
                    # round-off (transposes taken as inverses); without the projection the
                    # 20 s aggressive flight's rotations were 0.006 off orthonormal by frame 50
                    U, _, Vt = np.linalg.svd(self.window.pose(prev)[:3, :3] @ self._last_prediction_rotation @ R.T)
                    guess[:3, :3] = U @ Vt
                    self._tracked_guess = (timestamp, guess)
                T_w_c[:3, :3] = T_w_c[:3, :3] @ R.T
        model = model.copy()
        model.update(T_w_c, timestamp, measure_motion=True)
        self._prediction_basis = prediction_basis(model, self.window, timestamp, tracks.ids,
                                                  tracks.positions, est.prediction_depth_neighbours)

    def process(self, frame_id: int, timestamp: float, image: np.ndarray | None) -> FrameOutput:
        """Process one frame; ``image`` None marks a missing or corrupt image (skipped)."""
        start = time.perf_counter()
        if image is None:
            return self._skipped(timestamp, frame_id, None, None)
        tracks = self.flow.process(timestamp, image, predicted=self.predict_tracks(timestamp))
        self.note_tracks(timestamp, tracks)
        return self.finish(self.estimate(frame_id, timestamp, image, tracks, start))

    def estimate(self, frame_id: int, timestamp: float, image: np.ndarray,
                 tracks: OpticalFlowResult, start: float, prediction_ready=None):
        """The estimator's part of :meth:`process` given the frame's tracks: optimisation,
        keyframes, restart, motion model; then, with ``predict_before_estimate = false``, the
        next frame's prediction basis is fixed and ``prediction_ready()`` is called (e.g. to
        start the next frame's tracking); then Λ_scaledrift and marginalisation, which change
        nothing a prediction reads. Returns what :meth:`finish` needs, or the finished :class:`FrameOutput` of a
        skipped frame."""
        est = self.config.estimator
        if tracks.rejected is not None:  # blank / wrong size: the frontend kept its last frame
            return self._skipped(timestamp, frame_id, tracks, start)
        self._tracks[frame_id] = FrameTracks.from_result(tracks)
        self._gn_iterations, self._gn_converged = 0, None
        win = self.window
        starts_submap = self.state is MapState.EMPTY
        guess = np.eye(4) if starts_submap else self._initial_guess(timestamp)
        win.add_frame(frame_id, guess, is_keyframe=starts_submap)
        self._timestamps[frame_id] = timestamp
        keyframe_taken = False
        if starts_submap:
            self.triangulator.add_hosted_by(self._tracks, frame_id)  # all at infinity
            self.keyframe_log.append((frame_id, self.submap))
            keyframe_taken = True
        else:
            win.add_observations(frame_id, tracks.ids, tracks.positions, tracks.levels, skip_unknown=True)
        if est.refind_enabled:
            self.refinder.add_image(frame_id, image)
            if self.state is MapState.MAPPED and win.num_connected(frame_id)[0] < est.refind_below_finite:
                self.refinder.refind(frame_id, guess)

        finite, _ = win.num_connected(frame_id)
        initialized = (not starts_submap and finite < est.min_finite_observations
                       and self._try_initialization(frame_id))

        negative_entropy, diverged = None, False
        if len(win.frame_ids) > 1:
            try:
                negative_entropy, inserted = self._optimize_and_select_keyframe(frame_id)
                keyframe_taken |= inserted
            except (FloatingPointError, np.linalg.LinAlgError):
                diverged = True  # treated as a tracking failure below

        finite, infinite = win.num_connected(frame_id)
        T_w_c = win.pose(frame_id)
        submap = self.submap
        lost = diverged or (len(win.keyframe_ids) >= _FAILURE_MIN_KEYFRAMES
                            and finite + infinite < est.failure_min_connected)
        self.state, status = next_state(self.state, initialized=initialized, lost=lost)
        drift = None
        if lost:
            self._restart()
            T_w_c, submap = self._start_submap(frame_id, timestamp, tracks, image), self.submap
        else:
            if initialized:  # the pose jumped to the new map's: no motion to measure
                self.motion.forget_motion()
            self.motion.update(T_w_c, timestamp, measure_motion=self._previous_frame is not None
                               and self.state is MapState.MAPPED and not initialized)
            self._previous_frame = frame_id
        # the pose and the landmarks are final: the next frame's predictions are fixed here, so
        # its tracking may start (``prediction_ready``) while the rest runs
        if est.motion_guided_tracking and not est.predict_before_estimate:
            self._prediction_basis = prediction_basis(self.motion, win, timestamp, tracks.ids,
                                                      tracks.positions, est.prediction_depth_neighbours)
        if prediction_ready is not None:
            prediction_ready()
        if not lost:
            drift = self._scale_drift()  # final estimate, before marginalisation (Sec. V)
            keep = {self._init_reference} if (est.init_keep_reference and self.state is not MapState.MAPPED
                                              and self._init_reference in win) else set()
            marg = frames_to_marginalize(win, self.config.backend, keep, self._timestamps)
            if marg:
                win.marginalize(marg)
                for f in marg:
                    self._tracks.pop(f, None)
                    self._timestamps.pop(f, None)
                self.refinder.prune()
        # inverse distances of the frame's tracks in the final state: the frame's output
        inv = win.landmarks.inverse_distances(tracks.ids)
        return (start, timestamp, frame_id, tracks, status, submap, finite, infinite, keyframe_taken,
                negative_entropy, drift, T_w_c, inv, self._gn_iterations, self._gn_converged)

    def _scale_drift(self) -> ScaleDriftResult | Future:
        """Λ_scaledrift of the window now: the result, or its future on
        :attr:`scale_drift_executor` (the window is copied first)."""
        task = scale_drift_task(self.window, workspaces=self._scale_drift_workspaces)
        executor = self.scale_drift_executor
        return task() if executor is None else executor.submit(task)

    @staticmethod
    def complete(out: FrameOutput) -> FrameOutput:
        """``out`` with Λ_scaledrift filled in, waiting for its computation if it runs on
        another thread (:attr:`scale_drift_executor`); ``out`` itself when nothing is pending."""
        pending = out.scale_drift_pending
        if pending is None:
            return out
        _set_scale_drift(out.diagnostics, pending.result())
        return dataclasses.replace(out, scale_drift_pending=None)

    def finish(self, estimated) -> FrameOutput:
        """The rest of :meth:`process` after :meth:`estimate`: the frame's outputs. Reads the
        window, changes nothing that the next frame's tracking depends on (so the next frame's
        tracking may run meanwhile)."""
        if isinstance(estimated, FrameOutput):
            return estimated
        (start, timestamp, frame_id, tracks, status, submap, finite, infinite, keyframe_taken,
         negative_entropy, drift, T_w_c, inv, gn_iterations, gn_converged) = estimated
        est, win = self.config.estimator, self.window
        if status in (FrameStatus.TRACKING, FrameStatus.REINIT):
            seen = inv[inv > 0.0]
            if len(seen) >= est.scene_distance_min_points:
                self._scene_distance = float(np.mean(1.0 / seen))
        diag = FrameDiagnostics(
            timestamp, frame_id, submap, status.value, len(tracks), finite, infinite, keyframe_taken,
            negative_entropy if negative_entropy is not None and np.isfinite(negative_entropy) else None,
            (time.perf_counter() - start) * 1e3, gn_iterations=gn_iterations,
            gn_converged=gn_converged,
        )
        pending = drift if isinstance(drift, Future) else None
        if pending is None:
            _set_scale_drift(diag, drift)
        if self.export_landmarks:
            points, inv_dist = self.window_landmarks()
            return FrameOutput(T_w_c, diag, tracks, inv, tuple(win.keyframe_ids), points, inv_dist,
                               scale_drift_pending=pending)
        return FrameOutput(T_w_c, diag, tracks, inv, tuple(win.keyframe_ids),
                           scale_drift_pending=pending)


def _set_scale_drift(diag: FrameDiagnostics, drift: ScaleDriftResult | None) -> None:
    """The indicator fields of the diagnostics (None: not computed or not defined)."""
    diag.scale_drift_indicator = drift.value if drift is not None else None
    diag.scale_drift_indicator_ref = drift.value_ref if drift is not None else None
    diag.scale_drift_reason = drift.reason if drift is not None and drift.value is None else ""
