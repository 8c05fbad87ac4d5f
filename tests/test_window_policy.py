"""The estimator's window policy: which frames leave the sliding window."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend import BackendConfig, SlidingWindow
from granite.backend.synthetic import build_window, default_camera, make_scene
from granite.estimator.window_policy import frames_to_marginalize

CFG = BackendConfig(max_frames=3, max_keyframes=4)


def test_keyframe_that_lost_its_landmarks_leaves_first():
    scene = make_scene(num_frames=9, num_points=150, sigma=0.5, recent_frames=3, seed=50)
    win = build_window(scene, CFG, seed=51)
    win.make_keyframe(scene.frame_ids[-3])  # a recent frame promoted: never chosen
    # 6 old keyframes + the promoted one > 4: keyframe 0's landmarks are not seen in the newest
    # frame any more (landmarks are observed in at most 5 consecutive frames)
    seen = win.landmarks.observed_in(scene.frame_ids[-1])
    assert not (win.landmarks.hosted_by(scene.frame_ids[0]) & seen)
    assert frames_to_marginalize(win, CFG) == [scene.frame_ids[0]]


def _line_window(keyframe_x: list[float]) -> SlidingWindow:
    """Keyframes 0..K-1 at the given x positions on a line, then three recent frames beyond the
    last one; every keyframe hosts one landmark that the newest frame sees (so no keyframe has
    lost its landmarks and the distance score decides)."""
    win = SlidingWindow(default_camera(), CFG)
    frames = list(keyframe_x) + [keyframe_x[-1] + 0.5 * (k + 1) for k in range(3)]
    for fid, x in enumerate(frames):
        T = np.eye(4)
        T[0, 3] = x
        win.add_frame(fid, T, is_keyframe=fid < len(keyframe_x))
    newest = len(frames) - 1
    for fid in range(len(keyframe_x)):
        win.add_landmark(100 + fid, fid, np.array([0.0, 0.0, 1.0]), 0.1)
        win.add_observation(100 + fid, fid, np.array([319.5, 239.5]))
        win.add_observation(100 + fid, newest, np.array([319.5, 239.5]))
    return win


@pytest.mark.parametrize("close_x, expected", [(0.01, 0), (-0.01, 1)])
def test_full_window_drops_the_largest_distance_score(close_x, expected):
    """Keyframes at x = 0 (id 0), close_x (id 1), 2, 3, 4, 5 m. The pair 0/1 is 1 cm apart, so
    the term 1 / 0.01 dominates both their sums (every other term is below 1 / 1.99); the factor
    sqrt(|t_k - t_last|) then makes the member farther from the newest keyframe the largest DSO
    score. A smallest-score rule (the reference code's) would choose a keyframe without a close
    neighbour instead, never 0 or 1."""
    win = _line_window([0.0, close_x, 2.0, 3.0, 4.0, 5.0])
    assert frames_to_marginalize(win, CFG) == [expected]


def test_old_non_keyframes_always_leave():
    win = build_window(make_scene(num_frames=8, num_points=100, keyframe_every=2, seed=52), CFG)
    ids = win.frame_ids
    old_nonkf = [g for g in ids[:-3] if not win.is_keyframe(g)]
    assert old_nonkf and set(old_nonkf) <= set(frames_to_marginalize(win, CFG))
    assert not set(ids[-3:]) & set(frames_to_marginalize(win, CFG))
