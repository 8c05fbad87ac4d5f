"""The keyframe-turnover rules of ours (all off by default): a keyframe when the scene scale
changed (``[estimator] keyframe_depth_change``), and the marginalisation of keyframes that saw
the scene at another scale (``[backend] marg_depth_change``) or are too old
(``[backend] marg_max_keyframe_age``).

The windows are built from an explicit geometry (downward-looking cameras over rough ground);
the expected depths are computed from the generated world points, not by the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from granite.backend import BackendConfig, SlidingWindow
from granite.backend.synthetic import default_camera
from granite.estimator.config import EstimatorConfig, VoConfig
from granite.estimator.keyframes import depth_ratio_exceeds, median_depth
from granite.estimator.vo import MonocularVO
from granite.estimator.window_policy import frames_to_marginalize
from granite.geometry import se3_inverse

CFG = BackendConfig(max_frames=3, max_keyframes=4)


def _down(x: float, height: float) -> np.ndarray:
    """Camera at (x, 0, height) looking straight down (CV: z forward = -world z)."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [x, 0.0, height]
    return T


class PlaneWindow:
    """Frames ``(x, height, is_keyframe)`` in that order (ids 0, 1, ..); every keyframe hosts
    ``points_per_keyframe`` landmarks on rough ground (z in [-1, 1]) below it, observed in the
    host and, where they project into the image, in the newest frame. ``scale`` multiplies
    the whole world (poses and points)."""

    def __init__(self, frames, points_per_keyframe: int = 40, scale: float = 1.0,
                 config: BackendConfig = CFG, seed: int = 0, window: SlidingWindow | None = None):
        rng = np.random.default_rng(seed)
        cam = default_camera()
        self.win = window if window is not None else SlidingWindow(cam, config)
        self.points: dict[int, np.ndarray] = {}
        poses = []
        for fid, (x, h, kf) in enumerate(frames):
            T = _down(x, h)
            T[:3, 3] *= scale
            poses.append(T)
            self.win.add_frame(fid, T, is_keyframe=kf)
        newest = len(frames) - 1
        lm = 1000
        for fid, (x, h, kf) in enumerate(frames):
            if not kf:
                continue
            # ground points inside the host's view (and, for the test scenes, the newest's)
            px = rng.uniform(-0.3, 0.3, points_per_keyframe) * h + x
            py = rng.uniform(-0.2, 0.2, points_per_keyframe) * h
            pz = rng.uniform(-1.0, 1.0, points_per_keyframe)
            for p in np.column_stack([px, py, pz]) * scale:
                p_h = (se3_inverse(poses[fid]) @ np.append(p, 1.0))[:3]
                dist = float(np.linalg.norm(p_h))
                self.win.add_landmark(lm, fid, p_h / dist, 1.0 / dist)
                uv, ok = cam.project(p_h[None])
                self.win.add_observation(lm, fid, uv[0])
                p_n = (se3_inverse(poses[newest]) @ np.append(p, 1.0))[:3]
                uv_n, ok_n = cam.project(p_n[None])
                if newest != fid and ok_n[0] and 0 <= uv_n[0, 0] < cam.width and 0 <= uv_n[0, 1] < cam.height:
                    self.win.add_observation(lm, newest, uv_n[0])
                self.points[lm] = p
                lm += 1
        self.poses = poses

    def true_median_depth(self, frame_id: int) -> float:
        """Median camera z of the generated points connected to a frame (observed or hosted),
        from the generator's world points."""
        db = self.win.landmarks
        ids = db.observed_in(frame_id) | db.hosted_by(frame_id)
        T_c_w = se3_inverse(self.poses[frame_id])
        z = [(T_c_w @ np.append(self.points[i], 1.0))[2] for i in ids]
        return float(np.median(z))


# ------------------------------------------------------------------------------ median depth
def test_median_depth_is_the_median_camera_z_of_the_connected_finite_landmarks():
    scene = PlaneWindow([(0.0, 10.0, True), (1.0, 10.5, True), (2.0, 12.0, False)], seed=1)
    win = scene.win
    for fid in win.frame_ids:
        assert median_depth(win, fid) == pytest.approx(scene.true_median_depth(fid), rel=1e-9)
    # points at infinity carry no depth: set half of frame 0's to d = 0, the median follows
    # the others
    hosted = sorted(win.landmarks.hosted_by(0))
    for lm in hosted[::2]:
        win.set_inverse_distance(lm, 0.0)
    kept = [lm for lm in hosted if lm not in hosted[::2]]
    T_c_w = se3_inverse(scene.poses[0])
    expected = np.median([(T_c_w @ np.append(scene.points[i], 1.0))[2] for i in kept])
    assert median_depth(win, 0) == pytest.approx(expected, rel=1e-9)


def test_median_depth_is_undefined_with_too_few_finite_landmarks():
    scene = PlaneWindow([(0.0, 10.0, True), (0.5, 10.0, False)], points_per_keyframe=4)
    assert median_depth(scene.win, 0) is None and median_depth(scene.win, 1) is None
    scene = PlaneWindow([(0.0, 10.0, True), (0.5, 10.0, False)], points_per_keyframe=5)
    assert median_depth(scene.win, 0) is not None


def test_depth_ratio_threshold_is_symmetric_and_off_at_zero():
    assert depth_ratio_exceeds(13.0, 10.0, 0.25) and not depth_ratio_exceeds(12.0, 10.0, 0.25)
    assert depth_ratio_exceeds(7.9, 10.0, 0.25) and not depth_ratio_exceeds(8.1, 10.0, 0.25)
    assert not depth_ratio_exceeds(40.0, 4.0, 0.0)
    assert not depth_ratio_exceeds(None, 4.0, 0.25) and not depth_ratio_exceeds(4.0, None, 0.25)


# ---------------------------------------------------------------- scene-scale keyframe (a)
def _vo_with_window(frames, change: float, scale: float = 1.0) -> MonocularVO:
    vo = MonocularVO(default_camera(), VoConfig(estimator=EstimatorConfig(keyframe_depth_change=change)))
    PlaneWindow(frames, scale=scale, window=vo.window, seed=3)
    return vo


@pytest.mark.parametrize("scale", [1.0, 0.07, 12.0])
@pytest.mark.parametrize("height, fires", [(10.5, False), (12.0, False), (13.5, True),   # climb
                                           (8.5, False), (7.5, True), (4.0, True)])      # descent
def test_scene_scale_keyframe_fires_when_the_depth_changed_by_the_factor(height, fires, scale):
    """Newest keyframe at 10 m over ground in [-1, 1] m, the current frame at ``height``:
    with ``keyframe_depth_change = 0.25`` the criterion fires when the generated median depths
    differ by more than 1.25 either way, whatever the scale of the world."""
    frames = [(0.0, 10.0, True), (0.3, 10.0, True), (0.6, height, False)]
    vo = _vo_with_window(frames, 0.25, scale)
    truth = PlaneWindow(frames, seed=3)
    scene_ratio = truth.true_median_depth(2) / truth.true_median_depth(1)
    assert (abs(math.log(scene_ratio)) > math.log(1.25)) == fires  # the test's own geometry
    assert vo._scene_scale_changed(2) == fires
    off = MonocularVO(default_camera(), VoConfig())  # the default: off
    PlaneWindow(frames, scale=scale, window=off.window, seed=3)
    assert not off._scene_scale_changed(2)


# ------------------------------------------------------------ depth marginalisation (b)
def _full_window(heights, **config) -> tuple[SlidingWindow, BackendConfig]:
    """5 keyframes (> max_keyframes 4) at x = 0, 0.2, .. and the given heights, then 3 recent
    frames at the last height; every keyframe's landmarks are seen by the newest frame, so the
    reference's "lost its landmarks" rule does not fire and its distance score decides."""
    cfg = BackendConfig(max_frames=3, max_keyframes=4, **config)
    frames = [(0.2 * k, h, True) for k, h in enumerate(heights)]
    frames += [(0.2 * (len(heights) + k), heights[-1], False) for k in range(3)]
    return PlaneWindow(frames, config=cfg, seed=5).win, cfg


def test_keyframe_at_another_scale_leaves_first():
    """Keyframes at 6, 20, 21, 21.05, 22 m; the newest frame at 22 m. The reference rule
    removes one of the close pair (largest DSO score); with marg_depth_change = 0.5 the 6 m
    keyframe (median depth ratio about 3.5 to the newest frame) goes."""
    heights = [6.0, 20.0, 21.0, 21.05, 22.0]
    win, ref = _full_window(heights)
    assert all(win.landmarks.hosted_by(k) <= win.landmarks.observed_in(win.frame_ids[-1])
               for k in win.keyframe_ids)
    reference_choice = frames_to_marginalize(win, ref)
    assert reference_choice in ([2], [3])
    win, cfg = _full_window(heights, marg_depth_change=0.5)
    assert frames_to_marginalize(win, cfg) == [0]
    # the farthest in depth wins among several beyond the factor
    win, cfg = _full_window([20.0, 6.0, 9.0, 21.05, 22.0], marg_depth_change=0.5)
    assert frames_to_marginalize(win, cfg) == [1]
    # a keyframe the caller keeps is never chosen
    win, cfg = _full_window(heights, marg_depth_change=0.5)
    assert frames_to_marginalize(win, cfg, keep={0}) == reference_choice


def test_keyframes_at_the_same_scale_keep_the_reference_order():
    heights = [18.0, 20.0, 21.0, 21.05, 22.0]  # all within a factor 1.5 of the newest frame
    win, ref = _full_window(heights)
    reference_choice = frames_to_marginalize(win, ref)
    win, cfg = _full_window(heights, marg_depth_change=0.5)
    assert frames_to_marginalize(win, cfg) == reference_choice


# --------------------------------------------------------------------- keyframe age (c)
def test_keyframe_older_than_the_maximum_age_leaves_first():
    heights = [20.0, 20.5, 21.0, 21.05, 22.0]
    win, ref = _full_window(heights)
    reference_choice = frames_to_marginalize(win, ref)
    ts = {f: 0.1 * f for f in win.frame_ids}  # 0 .. 0.7 s
    win, cfg = _full_window(heights, marg_max_keyframe_age=0.55)
    assert frames_to_marginalize(win, cfg, timestamps=ts) == [0]  # 0.7 s old
    ts_old = {**ts, 1: -5.0}
    assert frames_to_marginalize(win, cfg, timestamps=ts_old) == [1]  # the oldest first
    assert frames_to_marginalize(win, cfg, keep={0}, timestamps=ts) == [1]  # 0.6 s old
    win, cfg = _full_window(heights, marg_max_keyframe_age=5.0)  # none that old
    assert frames_to_marginalize(win, cfg, timestamps=ts) == reference_choice
    assert reference_choice != [0]


def test_keyframe_age_is_a_time_horizon_that_keeps_three_keyframes():
    """Not full (5 keyframes, max_keyframes 11): without the age rule nothing leaves; with it
    the oldest keyframe beyond the horizon leaves, one per call, down to 3 keyframes."""
    heights = [20.0, 20.5, 21.0, 21.05, 22.0]
    frames = [(0.2 * k, h, True) for k, h in enumerate(heights)] + [(1.0 + 0.2 * k, 22.0, False) for k in range(3)]
    ts = {f: float(f) for f in range(len(frames))}  # 1 s apart; the newest at 7 s
    cfg = BackendConfig(max_frames=3, max_keyframes=11, marg_max_keyframe_age=4.5)
    win = PlaneWindow(frames, config=cfg, seed=6).win
    assert frames_to_marginalize(win, BackendConfig(max_frames=3, max_keyframes=11), timestamps=ts) == []
    removed = []
    for _ in range(4):
        marg = frames_to_marginalize(win, cfg, timestamps=ts)
        removed += marg
        if marg:
            win.marginalize(marg)
    # keyframes 0 (7 s old), 1 (6 s) and 2 (5 s) are beyond the horizon; keyframe 2 stays
    # because 3 keyframes (2, 3, 4) must remain
    assert removed == [0, 1]
    assert win.keyframe_ids == [2, 3, 4]
    assert frames_to_marginalize(win, cfg, timestamps=ts) == []
    # without timestamps the rule cannot act
    win2 = PlaneWindow(frames, config=cfg, seed=6).win
    assert frames_to_marginalize(win2, cfg) == []


# ------------------------------------------------------------------ scale-link keyframe
def test_scale_link_keyframe_is_taken_whenever_too_few_landmarks_carry_the_scale(monkeypatch):
    """``keyframe_min_scale_links = N``: on the pre-rendered ``rotation`` asset, every
    keyframe decision that counted fewer than N finite landmarks seen in two keyframes (and
    came more than ``min_frames_after_keyframe`` frames after a keyframe) inserted one, and
    the count of each decision is the brute-force count over the window."""
    from pathlib import Path

    from granite.backend.landmarks import LandmarkDatabase
    from granite.io import open_dataset

    calls = []
    count = LandmarkDatabase.num_scale_links

    def recording(self, frame_id, keyframes):
        keyframes = list(keyframes)
        n = count(self, frame_id, keyframes)
        expected = sum(1 for lm in self.observed_in(frame_id)
                       if self.inverse_distances(np.array([lm]))[0] > 0.0
                       and len(set(self.observations(lm)) & (set(keyframes) - {frame_id})) >= 2)
        calls.append((frame_id, n, expected))
        return n

    monkeypatch.setattr(LandmarkDatabase, "num_scale_links", recording)
    ds = open_dataset(Path(__file__).resolve().parents[1] / "assets" / "sequences" / "rotation")
    links = 55  # the flight's counts are 51-57 without the rule
    vo = MonocularVO(ds.calibration.camera(), VoConfig.from_dict({"estimator": {"keyframe_min_scale_links": links}}))
    diags = {i: vo.process(i, f.timestamp, f.image).diagnostics for i, f in enumerate(ds.frames(0, len(ds)))}
    assert calls and all(n == expected for _, n, expected in calls)
    fired = [f for f, n, _ in calls if n < links]
    assert fired and len(fired) < len(calls)
    assert all(diags[f].keyframe for f in fired)
