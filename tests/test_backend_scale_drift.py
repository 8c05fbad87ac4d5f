"""Scale-drift indicator Λ_scaledrift (granite.backend.scale_drift, paper Sec. V, Eq. 11-17).

Synthetic windows (granite.backend.synthetic); every expected value is computed independently
(finite differences, re-built transformed worlds, Monte Carlo of the optimiser).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from granite.backend import (
    BackendConfig,
    KeyframeSystem,
    SlidingWindow,
    chain_jacobian,
    chain_jacobian_inverse,
    indicator_from_information,
    keyframe_system,
    marginalize_dense,
    pose_delta,
    relative_poses,
    relative_translation_information,
    WorkspacePool,
    scale_drift_indicator,
    scale_drift_of_system,
    scale_drift_task,
)
from granite.backend.reprojection import reprojection_residuals
from granite.backend.scale_drift import NO_SCALE_ANCHOR, NO_SCALE_LINK
from granite.backend.synthetic import make_scene
from granite.estimator.diagnostics import FrameDiagnostics, diagnostics_to_csv, read_diagnostics
from granite.geometry import decoupled_increment, so3_exp


def _random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    P = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        P[k, :3, :3] = so3_exp(rng.normal(0.0, 1.0, 3))
        P[k, :3, 3] = rng.normal(0.0, 2.0, 3)
    return P


def _compose(P0: np.ndarray, S: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Absolute poses from the chain: oldest pose and relative poses, each with its decoupled
    increment from ``y`` (6n,)."""
    out = [decoupled_increment(P0, y[:6])]
    for k in range(len(S)):
        out.append(out[-1] @ decoupled_increment(S[k], y[6 + 6 * k:12 + 6 * k]))
    return np.array(out)


def test_chain_jacobian_matches_finite_differences_and_is_inverted_exactly():
    P = _random_poses(5, seed=2)
    S = relative_poses(P)
    assert np.allclose(_compose(P[0], S, np.zeros(30)), P, atol=1e-12)
    J = chain_jacobian(P)
    eps = 1e-6
    J_num = np.zeros_like(J)
    for i in range(30):
        e = np.zeros(30)
        e[i] = eps
        plus, minus = _compose(P[0], S, e), _compose(P[0], S, -e)
        J_num[:, i] = np.concatenate([pose_delta(plus[k], P[k]) - pose_delta(minus[k], P[k])
                                      for k in range(5)]) / (2 * eps)
    assert np.abs(J - J_num).max() < 1e-7
    assert np.abs(chain_jacobian_inverse(P) @ J - np.eye(30)).max() < 1e-12
    assert np.abs(J @ chain_jacobian_inverse(P) - np.eye(30)).max() < 1e-12


def _world(Q: np.ndarray, p: np.ndarray, s: float):
    def move(T: np.ndarray) -> np.ndarray:
        out = np.eye(4)
        out[:3, :3] = Q @ T[:3, :3]
        out[:3, 3] = s * Q @ T[:3, 3] + p
        return out
    return move


def _window(scene, move, s: float, scale_fix: bool, marginalize_first: bool,
            config: BackendConfig | None = None, perturb_seed: int = 5) -> SlidingWindow:
    """The scene's window in a world moved by ``move`` (rotation, translation, scale ``s``):
    poses moved, inverse distances / s, scale-fix length * s and weight / s^2; optionally the
    first keyframe marginalised, then every pose perturbed (the same body-frame motion, its
    translation * s) so that prior states sit away from their linearisation points."""
    win = SlidingWindow(scene.camera, config)
    for k, fid in enumerate(scene.frame_ids):
        win.add_frame(fid, move(scene.poses[k]), is_keyframe=scene.keyframe[k])
    for i, lm in enumerate(scene.lm_ids):
        win.add_landmark(lm, scene.lm_host[i], scene.lm_bearing[i], scene.lm_inv_dist[i] / s)
    for lm, fid, uv, level in scene.observations:
        win.add_observation(lm, fid, uv, level)
    kfs = win.keyframe_ids
    if scale_fix:
        length = np.linalg.norm(scene.pose_of(kfs[0])[:3, 3] - scene.pose_of(kfs[1])[:3, 3])
        win.set_scale_fix(kfs[0], kfs[1], s * length, weight=1e8 / s ** 2)
    if marginalize_first:
        win.marginalize([kfs[0]])
    rng = np.random.default_rng(perturb_seed)
    for fid in win.frame_ids:
        d = np.eye(4)
        d[:3, :3] = so3_exp(rng.normal(0.0, 2e-3, 3))
        d[:3, 3] = s * rng.normal(0.0, 5e-3, 3)
        win.set_pose(fid, win.pose(fid) @ d)
    return win


@pytest.mark.parametrize("marginalize_first", [False, True])
def test_indicator_is_invariant_to_rotation_translation_and_scale_of_the_world(marginalize_first):
    scene = make_scene(num_frames=7, num_points=250, seed=4, obs_per_landmark=4)
    config = BackendConfig(max_inv_dist=100.0)  # the 0.04 world has inverse distances up to 6.25
    base = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, marginalize_first,
                   config)
    ref = scale_drift_indicator(base)
    assert ref.defined and ref.value_ref is not None
    if marginalize_first:  # the scale fix moved into the prior, prior states are off their FEJ points
        assert base.scale_fix is None and len(base.prior.frame_ids) > 1
    for Q, p, s in [(so3_exp(np.array([0.4, -1.1, 2.0])), np.array([30.0, -7.0, 2.5]), 1.0),
                    (np.eye(3), np.array([-3.0, 1.0, 100.0]), 1.0),
                    (np.eye(3), np.zeros(3), 7.5),
                    (so3_exp(np.array([-2.2, 0.3, 0.9])), np.array([1.0, 2.0, -3.0]), 0.04)]:
        res = scale_drift_indicator(_window(scene, _world(Q, p, s), s, True, marginalize_first,
                                            config))
        assert res.value == pytest.approx(ref.value, rel=1e-6)
        assert res.value_ref == pytest.approx(ref.value_ref, rel=1e-6)
        assert res.mean_translation == pytest.approx(s * ref.mean_translation, rel=1e-9)


def test_no_scale_anchor_is_not_defined_and_holding_the_oldest_keyframe_fixed_would_invent_one():
    scene = make_scene(num_frames=7, num_points=250, seed=4, obs_per_landmark=4)
    ident = _world(np.eye(3), np.zeros(3), 1.0)
    # gauge prior only (no scale fix), before and after it propagated through marginalisation
    for marg in (False, True):
        win = _window(scene, ident, 1.0, scale_fix=False, marginalize_first=marg)
        res = scale_drift_indicator(win)
        assert res.value is None and res.value_ref is None
        assert res.reason == NO_SCALE_ANCHOR
        assert res.lambda_min <= 1e-11 * res.lambda_max
    # the trap: with the propagated gauge prior, fixing the oldest keyframe's absolute pose
    # (instead of marginalising it) turns that prior into scale information that does not exist
    system = keyframe_system(win)
    n = len(system.frame_ids)
    J = chain_jacobian(system.poses_lin)
    H_rel = (J.T @ system.H @ J)[6:, 6:]  # oldest keyframe held fixed: rows/columns dropped
    keep = np.array([6 * k + i for k in range(n - 1) for i in range(3)])
    H_t, _ = marginalize_dense(H_rel, np.zeros(len(H_rel)), keep,
                               np.setdiff1d(np.arange(len(H_rel)), keep))
    vals = np.linalg.eigvalsh(H_t)
    assert vals[0] > 1e-6 * vals[-1]


def test_keyframe_system_is_the_keyframe_observations_hessian_with_non_keyframes_marginalised():
    scene = make_scene(num_frames=9, num_points=300, seed=7, obs_per_landmark=4, recent_frames=3)
    win = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, True)
    system = keyframe_system(win)
    kfs = win.keyframe_ids
    assert system.frame_ids == tuple(kfs) and len(kfs) < len(win.frame_ids)
    problem = win.problem(target_filter=set(kfs))  # every landmark, keyframe observations
    cost = win.cost_terms()
    full = cost.system(problem, *cost.linearize(problem), cost.no_motion_pairs(problem))
    rows = np.concatenate([np.arange(6 * problem.index[f], 6 * problem.index[f] + 6) for f in kfs])
    np.testing.assert_allclose(system.H_reprojection, full.H_reprojection[np.ix_(rows, rows)],
                               rtol=1e-9, atol=1e-9 * np.abs(system.H_reprojection).max())
    H_pose = full.H_prior + full.H_scale_fix + full.H_no_motion
    other = np.setdiff1d(np.arange(len(H_pose)), rows)
    expected, _ = marginalize_dense(H_pose, np.zeros(len(H_pose)), rows, other)
    np.testing.assert_allclose(system.H_priors, expected, rtol=1e-9, atol=1e-6)


def _numerical_relative_translation_information(win: SlidingWindow) -> np.ndarray:
    """``H_t`` of a window whose states sit at their linearisation points, assembled without
    the backend's Jacobians, weights, landmark elimination, chain Jacobian or Schur
    complements: central differences of the weighted residuals (reprojection of the
    observations made in keyframes, gauge prior, scale fix) with respect to the chain
    parameters (oldest keyframe's twist, relative-pose increments) and the landmark parameters
    (stereographic bearing, inverse distance); Huber weights ``min(1, k/|r|) 2^-level / σ^2``;
    then the oldest pose, the relative rotations and the landmarks removed by orthogonal
    projection of the translation columns (SVD) - the information of the relative translations
    with everything else marginalised."""
    cfg = win.config
    kfs = win.keyframe_ids
    problem = win.problem(target_filter=set(kfs))
    pk = problem.packed
    K, M = len(problem.frame_ids), pk.num_landmarks
    P = np.array([win.pose(f) for f in kfs])
    S = relative_poses(P)
    kf_rows = np.array([problem.index[f] for f in kfs])
    r0, _ = reprojection_residuals(win.camera, pk, problem.poses)
    e = np.linalg.norm(r0, axis=1)
    w = np.minimum(1.0, cfg.huber_threshold / np.maximum(e, 1e-300)) * 2.0 ** -pk.obs_level
    sw = np.sqrt(w / cfg.obs_std_dev ** 2)
    gauge_f = win.prior.frame_ids[0]
    assert win.prior.frame_ids == [gauge_f] and gauge_f == kfs[0]
    T_gauge = win.prior.lin_poses[gauge_f]
    sf = win.scale_fix
    si, sj = kfs.index(sf.frame_i), kfs.index(sf.frame_j)

    def residuals(y: np.ndarray, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        poses = problem.poses.copy()
        poses[kf_rows] = _compose(P[0], S, y)
        pk.lm_s[:], pk.lm_d[:] = s, d
        r, _ = reprojection_residuals(win.camera, pk, poses)
        T0 = poses[kf_rows[0]]
        gauge = np.concatenate([T0[:3, 3] - T_gauge[:3, 3],
                                _so3_log(T0[:3, :3] @ T_gauge[:3, :3].T)])
        ti, tj = poses[kf_rows[si]][:3, 3], poses[kf_rows[sj]][:3, 3]
        return np.concatenate([(sw[:, None] * r).ravel(),
                               math.sqrt(cfg.initial_pose_weight) * gauge,
                               [math.sqrt(sf.weight) * (np.linalg.norm(ti - tj) - sf.length)]])

    n = len(kfs)
    s0, d0 = pk.lm_s.copy(), pk.lm_d.copy()
    y0 = np.zeros(6 * n)
    cols = []
    eps = 1e-6
    for i in range(6 * n):
        dy = np.zeros(6 * n)
        dy[i] = eps
        cols.append((residuals(y0 + dy, s0, d0) - residuals(y0 - dy, s0, d0)) / (2 * eps))
    for i in range(M):
        for c in range(3):
            s_p, s_m, d_p, d_m = s0.copy(), s0.copy(), d0.copy(), d0.copy()
            if c < 2:
                s_p[i, c] += eps
                s_m[i, c] -= eps
            else:
                d_p[i] += eps
                d_m[i] -= eps
            cols.append((residuals(y0, s_p, d_p) - residuals(y0, s_m, d_m)) / (2 * eps))
    pk.lm_s[:], pk.lm_d[:] = s0, d0
    J = np.array(cols).T
    keep = np.array([6 * (k + 1) + c for k in range(n - 1) for c in range(3)])
    nuisance = np.setdiff1d(np.arange(J.shape[1]), keep)
    A = J[:, nuisance]
    A = A[:, np.abs(A).max(axis=0) > 0.0]  # landmarks only seen by their host: zero columns
    U, sv, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, sv > 1e-10 * sv.max()]
    Jt = J[:, keep] - U @ (U.T @ J[:, keep])
    return Jt.T @ Jt


def _so3_log(R: np.ndarray) -> np.ndarray:
    c = np.clip(0.5 * (np.trace(R) - 1.0), -1.0, 1.0)
    theta = math.acos(c)
    W = 0.5 * (R - R.T) * (theta / math.sin(theta) if theta > 1e-12 else 1.0)
    return np.array([W[2, 1], W[0, 2], W[1, 0]])


def test_relative_translation_information_matches_a_dense_finite_difference_computation():
    """End-to-end check of the information Λ is computed from: observation noise, pyramid
    levels 0-2 and a Huber threshold that down-weights part of the observations, two recent
    non-keyframes (their observations must not count), the gauge prior and the scale fix."""
    scene = make_scene(num_frames=7, num_points=120, seed=3, obs_per_landmark=4, max_level=2,
                       recent_frames=2)
    config = BackendConfig(huber_threshold=0.6, no_motion_weight=0.0)
    win = SlidingWindow(scene.camera, config)
    for k, fid in enumerate(scene.frame_ids):
        win.add_frame(fid, scene.poses[k], is_keyframe=scene.keyframe[k])
    for i, lm in enumerate(scene.lm_ids):
        win.add_landmark(lm, scene.lm_host[i], scene.lm_bearing[i], scene.lm_inv_dist[i])
    for lm, fid, uv, level in scene.observations:
        win.add_observation(lm, fid, uv, level)
    kfs = win.keyframe_ids
    length = float(np.linalg.norm(win.pose(kfs[0])[:3, 3] - win.pose(kfs[2])[:3, 3]))
    win.set_scale_fix(kfs[0], kfs[2], 1.01 * length, weight=1e4)
    assert len(kfs) == 5 and len(win.frame_ids) == 7
    problem = win.problem(target_filter=set(kfs))
    lin, _ = win.cost_terms().linearize(problem)
    huber = lin.w < 2.0 ** -problem.packed.obs_level / config.obs_std_dev ** 2 * (1 - 1e-12)
    assert 0.1 < np.mean(huber[lin.w > 0]) < 0.9  # Huber is active on part of the observations
    expected = _numerical_relative_translation_information(win)
    system = keyframe_system(win)
    H_t = relative_translation_information(system.H, system.poses_lin)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(H_t, expected, rtol=0, atol=1e-7 * scale)  # measured 3e-10
    lam, lam_num = np.linalg.eigvalsh(H_t), np.linalg.eigvalsh(expected)
    np.testing.assert_allclose(lam, lam_num, rtol=1e-6, atol=1e-8 * scale)
    result = scale_drift_indicator(win)
    mean_t = np.mean(np.linalg.norm(relative_poses(system.poses)[:, :3, 3], axis=1))
    assert result.value == pytest.approx(1.0 / (math.sqrt(lam_num[0]) * mean_t), rel=1e-6)


def test_a_task_computes_the_indicator_of_the_window_as_it_was_when_the_task_was_made():
    """The concurrent pipeline makes the task at the frame's final estimate and runs it on
    another thread while the window is optimised and marginalised for the next frame."""
    from concurrent.futures import ThreadPoolExecutor

    scene = make_scene(num_frames=7, num_points=250, seed=4, obs_per_landmark=4)
    win = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, False)
    expected = scale_drift_indicator(win)
    assert expected.defined
    own = scale_drift_task(win, workspaces=WorkspacePool())
    shared = scale_drift_task(win)  # the window's buffers, which the next steps overwrite
    kfs = win.keyframe_ids
    win.optimize(max_iterations=3)
    win.marginalize([kfs[0]])
    win.set_pose(kfs[-1], win.pose(kfs[-1]) @ decoupled_increment(np.eye(4), np.full(6, 0.05)))
    changed = scale_drift_indicator(win)
    assert changed.value != expected.value  # the window did change what Λ reads
    with ThreadPoolExecutor(1) as pool:
        result = pool.submit(own).result()
    for res in (result, shared()):
        assert (res.value, res.value_ref, res.lambda_min, res.num_keyframes) == \
            (expected.value, expected.value_ref, expected.lambda_min, expected.num_keyframes)


def test_scale_fix_in_the_window_is_the_anchor_when_included_and_absent_when_excluded():
    scene = make_scene(num_frames=6, num_points=250, seed=6, obs_per_landmark=4)
    win = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, False)
    assert scale_drift_indicator(win, include_scale_fix=True).defined
    excluded = scale_drift_indicator(win, include_scale_fix=False)
    assert not excluded.defined and "scale" in excluded.reason


def test_fewer_than_three_keyframes_and_pure_rotation_are_not_defined():
    scene = make_scene(num_frames=6, num_points=200, seed=1, keyframe_every=3)
    win = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, False)
    assert len(win.keyframe_ids) == 2
    res = scale_drift_indicator(win)
    assert res.value is None and "keyframes" in res.reason
    rot = make_scene(num_frames=6, num_points=200, seed=1, pure_rotation=True)
    win = SlidingWindow(rot.camera)
    for k, fid in enumerate(rot.frame_ids):
        win.add_frame(fid, rot.poses[k], is_keyframe=True)
    for i, lm in enumerate(rot.lm_ids):
        win.add_landmark(lm, rot.lm_host[i], rot.lm_bearing[i], 0.0)  # at infinity
    for lm, fid, uv, level in rot.observations:
        win.add_observation(lm, fid, uv, level)
    win.set_scale_fix(rot.frame_ids[0], rot.frame_ids[1], 1.0)  # zero baseline: no direction
    res = scale_drift_indicator(win)
    assert res.value is None and res.value_ref is None


def test_non_finite_information_is_not_defined_never_nan():
    scene = make_scene(num_frames=5, num_points=200, seed=3)
    win = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, False)
    system = keyframe_system(win)
    H = system.H_reprojection.copy()
    H[3, 7] = H[7, 3] = np.nan
    bad = KeyframeSystem(system.frame_ids, system.poses, system.poses_lin, H, system.H_priors,
                         system.scale_fix_included)
    res = scale_drift_of_system(bad)
    assert res.value is None and res.value_ref is None and "non-finite" in res.reason
    value, value_ref, *_ = indicator_from_information(np.full((6, 6), np.inf), np.ones((2, 3)))
    assert value is None and value_ref is None
    indefinite = np.diag([-1e-3, 1.0, 2.0, 3.0, 4.0, 5.0])
    value, value_ref, lam_min, _, reason = indicator_from_information(indefinite, np.ones((2, 3)))
    assert value is None and value_ref is None and lam_min < 0 and "indefinite" in reason
    rows = [FrameDiagnostics(0.0, 0, 0, "tracking", scale_drift_indicator=float("nan"),
                             scale_drift_indicator_ref=float("inf")),
            FrameDiagnostics(0.05, 1, 0, "tracking", scale_drift_indicator=0.0123,
                             scale_drift_indicator_ref=0.006)]
    lines = diagnostics_to_csv(rows).splitlines()
    at = [lines[0].split(",").index(c) for c in ("scale_drift_indicator", "scale_drift_indicator_ref")]
    assert [lines[1].split(",")[i] for i in at] == ["", ""]
    assert [lines[2].split(",")[i] for i in at] == ["0.0123", "0.006"]


def test_diagnostics_columns_round_trip(tmp_path):
    path = tmp_path / "diagnostics.csv"
    rows = [FrameDiagnostics(0.0, 0, 0, "init"),
            FrameDiagnostics(0.05, 1, 0, "tracking", scale_drift_indicator=0.0123,
                             scale_drift_indicator_ref=0.006)]
    path.write_text(diagnostics_to_csv(rows))
    back = read_diagnostics(path)
    assert back[0].scale_drift_indicator is None and back[0].scale_drift_indicator_ref is None
    assert back[1].scale_drift_indicator == 0.0123 and back[1].scale_drift_indicator_ref == 0.006
    header = path.read_text().splitlines()[0].split(",")
    assert "scale_drift_indicator" in header and "scale_drift_indicator_ref" in header


def test_repeated_smallest_eigenvalue_gives_a_basis_independent_variant():
    rng = np.random.default_rng(8)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    lam = np.array([2.0, 2.0, 5.0, 9.0, 11.0, 40.0])
    t = rng.normal(size=(2, 3))
    c, s = math.cos(0.7), math.sin(0.7)
    Q2 = Q.copy()
    Q2[:, 0], Q2[:, 1] = c * Q[:, 0] + s * Q[:, 1], -s * Q[:, 0] + c * Q[:, 1]  # same eigenspace
    out = [indicator_from_information((B * lam) @ B.T, t) for B in (Q, Q2)]
    expected = 1.0 / (math.sqrt(2.0) * np.mean(np.linalg.norm(t, axis=1)))
    P = Q[:, :2] @ Q[:, :2].T
    expected_ref = 1.0 / (math.sqrt(2.0) * np.linalg.norm(np.diag(P) ** 0.25 * t.ravel()))
    for value, value_ref, lam_min, *_ in out:
        assert lam_min == pytest.approx(2.0, rel=1e-12)
        assert value == pytest.approx(expected, rel=1e-12)
        assert value_ref == pytest.approx(expected_ref, rel=1e-9)
    # a simple eigenvalue: the reference's sqrt(|q|) weights exactly
    lam[1] = 3.0
    value, value_ref, *_ = indicator_from_information((Q * lam) @ Q.T, t)
    q = Q[:, 0]
    assert value_ref == pytest.approx(
        1.0 / (math.sqrt(2.0) * np.linalg.norm(np.sqrt(np.abs(q)) * t.ravel())), rel=1e-9)


def test_indicator_rises_strictly_with_depth_at_a_fixed_baseline():
    values = []
    for factor in (1.0, 1.5, 2.0, 3.0, 4.5):
        scene = make_scene(num_frames=6, num_points=250, seed=9, obs_per_landmark=4, sigma=0.0,
                           depth=(4.0 * factor, 10.0 * factor))
        win = _window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0, True, False)
        res = scale_drift_indicator(win)
        assert res.defined
        values.append(res.value)
    assert all(b > a for a, b in zip(values, values[1:])), values


@pytest.mark.slow
def test_monte_carlo_log_scale_spread_matches_the_indicator():
    """200 noise draws of one window (scale fixed between its first two keyframes): the
    spread of the log scale of the estimated relative translations along the weakest
    direction agrees with Λ within 25 %."""
    scene = make_scene(num_frames=5, num_points=160, seed=12, obs_per_landmark=3, sigma=0.0,
                       depth=(6.0, 14.0))
    config = BackendConfig(huber_threshold=1e6, max_iterations=10)
    sigma = config.obs_std_dev

    def window(obs) -> SlidingWindow:
        win = SlidingWindow(scene.camera, config)
        for k, fid in enumerate(scene.frame_ids):
            win.add_frame(fid, scene.poses[k], is_keyframe=True)
        for i, lm in enumerate(scene.lm_ids):
            win.add_landmark(lm, scene.lm_host[i], scene.lm_bearing[i], scene.lm_inv_dist[i])
        for lm, fid, uv, level in obs:
            win.add_observation(lm, fid, uv, level)
        kfs = win.keyframe_ids
        length = np.linalg.norm(scene.pose_of(kfs[0])[:3, 3] - scene.pose_of(kfs[1])[:3, 3])
        win.set_scale_fix(kfs[0], kfs[1], length)
        return win

    truth = window(scene.observations)  # noise-free: the estimate is the truth
    res = scale_drift_indicator(truth)
    system = keyframe_system(truth)
    H_t = relative_translation_information(system.H, system.poses_lin)
    vals, vecs = np.linalg.eigh(H_t)
    q = vecs[:, 0].reshape(-1, 3)
    t_true = relative_poses(scene.poses)[:, :3, 3]
    u = t_true / np.linalg.norm(t_true, axis=1, keepdims=True)
    along = np.sum(q * u, axis=1)
    assert np.sum(along ** 2) > 0.9  # the weakest direction is a scale direction
    weights = along * np.linalg.norm(t_true, axis=1) / np.mean(np.linalg.norm(t_true, axis=1))
    rng = np.random.default_rng(21)
    stats = []
    for _ in range(200):
        obs = [(lm, fid, uv + rng.normal(0.0, sigma * 2.0 ** (0.5 * lvl), 2), lvl)
               for lm, fid, uv, lvl in scene.observations]
        win = window(obs)
        win.optimize()
        P = np.array([win.pose(f) for f in win.keyframe_ids])
        t_est = relative_poses(P)[:, :3, 3]
        log_scale = np.log(np.linalg.norm(t_est, axis=1) / np.linalg.norm(t_true, axis=1))
        stats.append(float(weights @ log_scale))
    spread = float(np.std(stats))
    print(f"Monte Carlo spread {spread:.5f}, Λ {res.value:.5f}")
    assert spread == pytest.approx(res.value, rel=0.25), (spread, res.value)


def test_links_seen_by_landmark_pairs_only_carry_no_scale_and_say_so():
    """Every landmark seen in its host and one more frame: the scale fix anchors the first
    link, and no landmark seen in three keyframes carries that scale to the others (two-view
    geometry has none), so Λ is not defined, for that reason, not for a missing anchor."""
    scene = make_scene(num_frames=6, num_points=300, seed=4, obs_per_landmark=2)
    res = scale_drift_indicator(_window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0,
                                        scale_fix=True, marginalize_first=False))
    assert res.value is None and res.reason == NO_SCALE_LINK
    assert res.lambda_min <= 1e-11 * res.lambda_max
    # the same scene with landmarks seen in four frames carries the scale along the chain
    scene = make_scene(num_frames=6, num_points=300, seed=4, obs_per_landmark=4)
    res = scale_drift_indicator(_window(scene, _world(np.eye(3), np.zeros(3), 1.0), 1.0,
                                        scale_fix=True, marginalize_first=False))
    assert res.defined and res.reason == ""


def test_the_null_direction_names_the_reason():
    """``H_t`` with a null direction along all relative translations (the scale of the whole
    chain) against one along a single link's translation."""
    rng = np.random.default_rng(3)
    t = rng.normal(size=(3, 3))
    Q, _ = np.linalg.qr(np.column_stack([t.ravel(), rng.normal(size=(9, 8))]))
    lam = np.concatenate([[0.0], rng.uniform(1.0, 10.0, 8)])
    *_, reason = indicator_from_information((Q * lam) @ Q.T, t)
    assert reason == NO_SCALE_ANCHOR
    e = np.zeros(9)
    e[3:6] = t[1] / np.linalg.norm(t[1])
    Q, _ = np.linalg.qr(np.column_stack([e, rng.normal(size=(9, 8))]))
    *_, reason = indicator_from_information((Q * lam) @ Q.T, t)
    assert reason == NO_SCALE_LINK


def test_chain_kernel_equals_the_dense_schur_complement_and_hands_singular_blocks_back():
    """The GIL-free kernel of ``relative_translation_information``: on a well-posed window the
    dense Schur complement ``H_kk - H_km H_mm^-1 H_mk`` of ``J^T H J`` (numpy inverse); with a
    marginalised direction without information it reports failure, and the public function
    falls back to the generalised inverse (finite, and the same as eliminating that direction
    by hand)."""
    from granite.backend.scale_drift import _chain_translation_information

    n = 4
    P = _random_poses(n, seed=7)
    rng = np.random.default_rng(3)
    A = rng.normal(size=(8 * n, 6 * n))
    H = A.T @ A  # positive definite
    J = chain_jacobian(P)
    Hr = J.T @ H @ J
    keep = np.array([6 * j + a for j in range(1, n) for a in range(3)])
    marg = np.setdiff1d(np.arange(6 * n), keep)
    expected = Hr[np.ix_(keep, keep)] - Hr[np.ix_(keep, marg)] @ np.linalg.inv(Hr[np.ix_(marg, marg)]) @ Hr[np.ix_(marg, keep)]
    ok, H_t = _chain_translation_information(H, P)
    assert ok
    assert np.allclose(H_t, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    assert np.array_equal(H_t, H_t.T)
    assert np.allclose(relative_translation_information(H, P), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())

    # no information on any rotation about x (keyframes at one place, unrotated: the chain
    # Jacobian is exact 0/1 blocks): marginalised directions without information, held with a
    # zero step by the generalised inverse
    P0 = np.tile(np.eye(4), (n, 1, 1))
    H0 = H.copy()
    rot_x = np.arange(3, 6 * n, 6)
    H0[rot_x, :] = 0.0
    H0[:, rot_x] = 0.0
    ok, _ = _chain_translation_information(H0, P0)
    assert not ok
    J0 = chain_jacobian(P0)
    Hr0 = J0.T @ H0 @ J0
    marg1 = np.setdiff1d(marg, rot_x)
    by_hand = Hr0[np.ix_(keep, keep)] - Hr0[np.ix_(keep, marg1)] @ np.linalg.inv(Hr0[np.ix_(marg1, marg1)]) @ Hr0[np.ix_(marg1, keep)]
    got = relative_translation_information(H0, P0)
    assert np.all(np.isfinite(got))
    assert np.allclose(got, by_hand, rtol=1e-6, atol=1e-7 * np.abs(by_hand).max())
