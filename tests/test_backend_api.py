"""Backend configuration, API contracts, Hessian access and negative entropy (paper Eq. 10)."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend import BackendConfig, SlidingWindow
from granite.backend.synthetic import build_window, default_camera, make_scene
from granite.errors import ConfigError


def test_config_defaults_are_the_reference_monocular_values():
    c = BackendConfig()
    assert (c.obs_std_dev, c.huber_threshold, c.infinite_obs_factor) == (0.5, 1.0, 0.01)
    assert (c.initial_pose_weight, c.scale_fix_weight) == (1e8, 1e8)
    assert c.no_motion_weight == 1e-6  # ours, above the pose system's round-off (docs/backend.md)
    assert (c.max_inv_dist, c.max_iterations, c.outlier_threshold) == (5.0, 7, 3.0)
    assert (c.max_frames, c.max_keyframes, c.use_lm) == (3, 11, False)


def test_config_from_dict_validates():
    assert BackendConfig.from_dict({"obs_std_dev": 1.0}).obs_std_dev == 1.0
    assert BackendConfig.from_dict(BackendConfig().to_dict()) == BackendConfig()
    with pytest.raises(ConfigError, match="unknown key.*obs_stddev"):
        BackendConfig.from_dict({"obs_stddev": 1.0})
    for bad in ({"obs_std_dev": 0.0}, {"max_iterations": 0}, {"max_iterations": 2.5},
                {"no_motion_weight": -1.0}, {"huber_threshold": float("nan")},
                {"use_lm": "yes"}):
        with pytest.raises(ConfigError):
            BackendConfig.from_dict(bad)


def test_api_contracts():
    win = SlidingWindow(default_camera())
    T = np.eye(4)
    win.add_frame(1, T, is_keyframe=True)
    win.add_frame(2, T)
    with pytest.raises(ValueError):
        win.add_frame(1, T)
    with pytest.raises(ValueError):
        win.add_frame(3, np.eye(3))
    with pytest.raises(ValueError, match="not a keyframe"):
        win.add_landmark(10, 2, np.array([0.0, 0.0, 1.0]), 0.5)
    with pytest.raises(ValueError):
        win.add_landmark(10, 1, np.array([0.0, 0.0, 1.0]), -0.1)
    win.add_landmark(10, 1, np.array([0.0, 0.0, 2.0]), 0.5)  # bearing is normalised
    np.testing.assert_allclose(win.landmarks.landmark(10).bearing, [0.0, 0.0, 1.0])
    with pytest.raises(KeyError):
        win.add_observation(10, 99, np.array([1.0, 2.0]))
    with pytest.raises(KeyError):
        win.add_observation(11, 1, np.array([1.0, 2.0]))
    with pytest.raises(ValueError):
        win.set_scale_fix(1, 1, 1.0)
    with pytest.raises(KeyError):
        win.marginalize([5])
    win.make_keyframe(2)
    assert win.keyframe_ids == [1, 2]
    # gauge prior on the first frame of an empty window only
    assert win.prior.frame_ids == [1]
    np.testing.assert_array_equal(win.prior.H, 1e8 * np.eye(6))
    win.reset()
    assert win.frame_ids == [] and len(win.landmarks) == 0 and win.prior.frame_ids == []
    assert SlidingWindow(default_camera(), BackendConfig(initial_pose_weight=0.0)).prior.H.size == 0


def test_database_bookkeeping():
    scene = make_scene(num_frames=5, num_points=60, seed=1)
    win = build_window(scene)
    db = win.landmarks
    assert db.num_observations == len(scene.observations)
    lm, f = scene.observations[3][:2]
    assert lm in db.observed_in(f) and f in db.observations(lm)
    win.remove_observation(lm, f)
    assert lm not in db.observed_in(f) and f not in db.observations(lm)
    host = db.landmark(lm).host_frame_id
    win.remove_landmark(lm)
    assert lm not in db and lm not in db.hosted_by(host)
    finite, infinite = win.num_connected(scene.frame_ids[2])
    assert infinite == 0 and finite == len(db.observed_in(scene.frame_ids[2]))
    some = next(iter(db.observed_in(scene.frame_ids[2])))
    win.set_inverse_distance(some, 0.0)
    assert win.num_connected(scene.frame_ids[2]) == (finite - 1, 1)
    direction, d = win.landmark_in_world(some)
    assert d == 0.0 and np.linalg.norm(direction) == pytest.approx(1.0)


def _optimised_window(seed=3):
    scene = make_scene(num_frames=6, num_points=150, seed=seed)
    win = build_window(scene, pose_noise=(0.01, 0.005), inv_dist_noise=0.1, seed=seed + 1)
    f = scene.frame_ids
    win.set_scale_fix(f[0], f[1], float(np.linalg.norm(scene.poses[1][:3, 3]
                                                       - scene.poses[0][:3, 3])))
    win.optimize()
    return scene, win


def test_pose_information_and_negative_entropy_match_the_covariance():
    scene, win = _optimised_window()
    hess = win.hessian_blocks()
    cov = np.linalg.inv(hess.H)
    for f in scene.frame_ids[1:]:
        blk = hess.block(f)
        info = win.pose_information(f)
        np.testing.assert_allclose(info, np.linalg.inv(cov[blk, blk]), rtol=1e-6)
        assert win.negative_entropy(f) == pytest.approx(-np.linalg.slogdet(cov[blk, blk])[1],
                                                        rel=1e-9)
        rot = cov[blk, blk][3:, 3:]
        assert win.negative_entropy(f, include_translation=False) == pytest.approx(
            -np.linalg.slogdet(rot)[1], rel=1e-9)
    # the components add up and the raw block dominates the reduced one (Schur complement)
    np.testing.assert_allclose(hess.H, hess.H_reprojection + hess.H_prior + hess.H_scale_fix
                               + hess.H_no_motion)
    gap = np.linalg.eigvalsh(hess.H_reprojection_raw - hess.H_reprojection)
    assert gap.min() > -1e-6 * np.abs(hess.H_reprojection_raw).max()


def test_negative_entropy_drops_with_fewer_observations():
    scene, win = _optimised_window(seed=5)
    newest = scene.frame_ids[-1]
    before = win.negative_entropy(newest)
    before_rot = win.negative_entropy(newest, include_translation=False)
    seen = sorted(win.landmarks.observed_in(newest))
    for lm in seen[: len(seen) // 2]:
        if win.landmarks.landmark(lm).host_frame_id != newest:
            win.remove_observation(lm, newest)
    assert win.negative_entropy(newest) < before
    assert win.negative_entropy(newest, include_translation=False) < before_rot


def test_snapshot_is_the_system_of_the_requested_iteration():
    scene = make_scene(num_frames=5, num_points=100, seed=7)
    win = build_window(scene, pose_noise=(0.01, 0.005), inv_dist_noise=0.1, seed=8)
    start = win.poses()
    report = win.optimize(max_iterations=5, snapshot_iteration=0)
    snap = report.snapshot
    assert snap.cost == report.costs[0]
    for k, f in enumerate(snap.frame_ids):
        np.testing.assert_array_equal(snap.poses[k], start[f])
    report = win.optimize(max_iterations=5, snapshot_iteration=4)
    assert report.snapshot.cost == report.costs[min(4, report.iterations - 1)]
