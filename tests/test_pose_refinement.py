"""Motion-only refinement of one frame's pose (``SlidingWindow.refine_pose``, used by the
re-optimisation after outlier removal): checked against the true pose of a noise-free
synthetic scene and against an independent least-squares solution (scipy) of the same
reprojection problem."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from granite.backend import BackendConfig, pose_delta
from granite.backend.synthetic import build_window, make_scene
from granite.geometry import decoupled_increment

NO_HUBER = BackendConfig(huber_threshold=1e6)


def _scene(sigma: float):
    # the last two frames are not keyframes: they host no landmark
    return make_scene(num_frames=8, num_points=200, sigma=sigma, recent_frames=2, seed=3)


def _perturbed(win, frame_id: int, xi) -> np.ndarray:
    T = decoupled_increment(win.pose(frame_id), np.asarray(xi, dtype=float))
    win.set_pose(frame_id, T)
    return T


def test_refinement_recovers_the_true_pose_and_changes_nothing_else():
    scene = _scene(sigma=0.0)
    win = build_window(scene)
    frame = scene.frame_ids[-1]
    _perturbed(win, frame, [0.05, -0.03, 0.04, 0.01, -0.02, 0.015])
    others = {f: win.pose(f).copy() for f in scene.frame_ids if f != frame}
    states = win.landmarks.states_of(scene.lm_ids)
    assert win.pose_refinable_alone(frame)
    report = win.refine_pose(frame, max_iterations=10)
    assert report.converged and not report.reverted
    assert report.final_cost < 1e-12 * report.initial_cost
    err = pose_delta(win.pose(frame), scene.pose_of(frame))
    assert np.max(np.abs(err)) < 1e-8
    for f, T in others.items():
        assert np.array_equal(win.pose(f), T)
    for a, b in zip(win.landmarks.states_of(scene.lm_ids), states):
        assert np.array_equal(a, b)


def test_refinement_reaches_the_least_squares_pose_of_its_observations():
    """With pixel noise the refined pose is the minimum of the frame's own reprojection cost,
    computed here independently: world points from the window, projection by the camera,
    scipy's Levenberg-Marquardt over the decoupled twist."""
    scene = _scene(sigma=0.5)
    win = build_window(scene, NO_HUBER)
    frame = scene.frame_ids[-1]
    start = _perturbed(win, frame, [0.02, 0.01, -0.03, -0.01, 0.005, 0.01])
    ids = sorted(win.landmarks.observed_in(frame))
    points = win.landmark_points(ids)
    uv = np.array([win.landmarks.observation(i, frame).uv for i in ids])

    def residuals(xi):
        T = decoupled_increment(start, xi)
        p = (points - T[:3, 3]) @ T[:3, :3]
        proj, valid = win.camera.project(p)
        assert np.all(valid)
        return (np.asarray(proj) - uv).ravel()

    expected = decoupled_increment(start, least_squares(residuals, np.zeros(6), method="lm",
                                                        xtol=1e-15, ftol=1e-15).x)
    win.refine_pose(frame, max_iterations=20)
    err = pose_delta(win.pose(frame), expected)
    assert np.max(np.abs(err[:3])) < 1e-7 and np.max(np.abs(err[3:])) < 1e-8
    # and the noise left it near, not at, the truth
    truth_err = pose_delta(win.pose(frame), scene.pose_of(frame))
    assert 1e-5 < np.linalg.norm(truth_err) < 1e-2


def test_a_step_that_raises_the_cost_is_undone():
    """From 2 m off, a Gauss-Newton step can overshoot (points leave the image, the robust
    weights change): such a step is undone, so the refined pose never has a higher cost than
    the start."""
    scene = _scene(sigma=0.5)
    frame = scene.frame_ids[-1]
    reverted = 0
    for seed in range(10):
        win = build_window(scene, seed=seed)
        rng = np.random.default_rng(seed)
        _perturbed(win, frame, np.concatenate([rng.normal(0, 2.0, 3), rng.normal(0, 0.05, 3)]))
        report = win.refine_pose(frame, max_iterations=1)
        assert report.final_cost <= report.initial_cost * (1 + 1e-9)
        reverted += report.reverted
    assert reverted >= 1  # measured: 1 of the 10 starts


def test_frames_that_host_landmarks_or_hold_the_scale_fix_are_not_refined_alone():
    scene = _scene(sigma=0.0)
    win = build_window(scene)
    host = scene.lm_host[0]
    assert not win.pose_refinable_alone(host)
    with pytest.raises(ValueError, match="cannot be refined alone"):
        win.refine_pose(host, max_iterations=2)
    last = scene.frame_ids[-1]
    win.set_scale_fix(scene.frame_ids[0], last, 1.0)
    assert not win.pose_refinable_alone(last)
    assert not win.pose_refinable_alone(12345)  # not in the window


def test_refinement_with_landmarks_recovers_the_true_pose_and_its_landmarks():
    """Pose and the landmarks it observes perturbed, other poses exact and fixed: both come
    back to the truth; landmarks the frame does not see and the other poses stay as they were."""
    scene = _scene(sigma=0.0)
    win = build_window(scene, bearing_noise=0.002, inv_dist_noise=0.05)
    frame = scene.frame_ids[-1]
    seen = sorted(win.landmarks.observed_in(frame))
    unseen = [i for i in scene.lm_ids if i not in set(seen)]
    truth = {i: (scene.lm_bearing[k], scene.lm_inv_dist[k]) for k, i in enumerate(scene.lm_ids)}
    unseen_states = win.landmarks.states_of(unseen)
    _perturbed(win, frame, [0.03, -0.02, 0.02, 0.01, -0.01, 0.005])
    others = {f: win.pose(f).copy() for f in scene.frame_ids if f != frame}
    report = win.refine_pose(frame, max_iterations=15, with_landmarks=True)
    assert report.final_cost < 1e-10 * report.initial_cost
    assert np.max(np.abs(pose_delta(win.pose(frame), scene.pose_of(frame)))) < 1e-7
    for f, T in others.items():
        assert np.array_equal(win.pose(f), T)
    for i in seen:
        lm = win.landmarks.landmark(i)
        assert np.linalg.norm(lm.bearing - truth[i][0]) < 1e-6
        assert abs(lm.inv_dist - truth[i][1]) < 1e-6 * truth[i][1] + 1e-9
    for a, b in zip(win.landmarks.states_of(unseen), unseen_states):
        assert np.array_equal(a, b)
