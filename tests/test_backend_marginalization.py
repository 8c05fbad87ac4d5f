"""Marginalisation: the prior against dense Schur complements, its null space (monocular gauge),
equivalence with the full problem, the scale fix moving into the prior, and the window kept at
its size by the estimator's policy."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend import BackendConfig, MargPrior, SlidingWindow, pose_delta
from granite.backend.reprojection import reprojection_residuals
from granite.backend.synthetic import build_window, make_scene
from granite.estimator.window_policy import frames_to_marginalize
from granite.geometry import decoupled_increment

LSQ = dict(huber_threshold=1e6)  # no robust down-weighting: exact quadratic comparisons


def _scene(seed=0, **kw):
    kw.setdefault("num_frames", 6)
    kw.setdefault("num_points", 150)
    return make_scene(sigma=0.5, seed=seed, **kw)


def _true_length(scene, i, j):
    return float(np.linalg.norm(scene.pose_of(i)[:3, 3] - scene.pose_of(j)[:3, 3]))


def _gauge_vectors(poses):
    """The 7 monocular gauge directions (3 translation, 3 rotation, scale) in the decoupled
    twists [v, w] of the given T_w_c, as columns (6n, 7)."""
    n = len(poses)
    N = np.zeros((6 * n, 7))
    for k, T in enumerate(poses):
        t = T[:3, 3]
        for a in range(3):
            e = np.zeros(3)
            e[a] = 1.0
            N[6 * k:6 * k + 3, a] = e  # global translation
            N[6 * k:6 * k + 3, 3 + a] = np.cross(e, t)  # rotation about the world origin
            N[6 * k + 3 + a, 3 + a] = 1.0
        N[6 * k:6 * k + 3, 6] = t  # scale
    return N


def _null_dim(H, rel=1e-9):
    d = np.sqrt(np.diag(H))
    Hs = H / d[:, None] / d[None, :]
    ev = np.linalg.eigvalsh(Hs)
    return int(np.sum(ev < rel * ev.max()))


def test_prior_equals_dense_schur_complement():
    """H_m, b_m of marginalising keyframe 0 with its landmarks equal the Schur complement of a
    dense system assembled from finite-difference Jacobians of those observations plus the
    gauge prior."""
    scene = _scene(seed=1)
    cfg = BackendConfig(landmark_damping=0.0, **LSQ)
    win = build_window(scene, cfg, pose_noise=(0.02, 0.01), bearing_noise=0.002,
                       inv_dist_noise=0.2, seed=2)
    f0 = scene.frame_ids[0]
    win.set_scale_fix(scene.frame_ids[1], scene.frame_ids[2],
                      _true_length(scene, scene.frame_ids[1], scene.frame_ids[2]))
    win.optimize(max_iterations=2)
    win.set_pose(f0, decoupled_increment(win.pose(f0), np.full(6, 1e-4)))  # off its prior mean
    hosted = sorted(win.landmarks.hosted_by(f0))
    problem = win.problem(hosted)
    pk = problem.packed
    K, M = len(problem.frame_ids), pk.num_landmarks
    eps = 1e-6

    def res(poses, s, d):
        pk.lm_s[:], pk.lm_d[:] = s, d
        return reprojection_residuals(win.camera, pk, poses)[0].reshape(-1)

    s0, d0 = pk.lm_s.copy(), pk.lm_d.copy()
    # first-estimate Jacobians: states of the prior (here frame 0 with its gauge prior) are
    # linearised at their linearisation point, the residual at the current estimate
    P_lin = problem.poses.copy()
    P_lin[problem.index[f0]] = win.prior.lin_poses[f0]
    J = np.zeros((2 * pk.num_observations, 6 * K + 3 * M))
    for idx in range(K):
        for c in range(6):
            xi = np.zeros(6)
            xi[c] = eps
            Pp, Pm = P_lin.copy(), P_lin.copy()
            Pp[idx] = decoupled_increment(Pp[idx], xi)
            Pm[idx] = decoupled_increment(Pm[idx], -xi)
            J[:, 6 * idx + c] = (res(Pp, s0, d0) - res(Pm, s0, d0)) / (2 * eps)
    for i in range(M):
        for c in range(3):
            sp, sm, dp, dm = s0.copy(), s0.copy(), d0.copy(), d0.copy()
            if c < 2:
                sp[i, c] += eps
                sm[i, c] -= eps
            else:
                dp[i] += eps
                dm[i] -= eps
            J[:, 6 * K + 3 * i + c] = (res(P_lin, sp, dp) - res(P_lin, sm, dm)) / (2 * eps)
    r = res(problem.poses, s0, d0)
    w = np.repeat(2.0 ** -pk.obs_level, 2) / cfg.obs_std_dev ** 2
    H = J.T @ (w[:, None] * J)
    b = J.T @ (w * r)
    k0 = problem.index[f0]
    H[6 * k0:6 * k0 + 6, 6 * k0:6 * k0 + 6] += cfg.initial_pose_weight * np.eye(6)
    b[6 * k0:6 * k0 + 6] += cfg.initial_pose_weight * pose_delta(win.pose(f0), scene.poses[0])
    marg = np.r_[np.arange(6 * k0, 6 * k0 + 6), np.arange(6 * K, 6 * K + 3 * M)]
    keep_frames = [f for f in problem.frame_ids if f != f0]
    keep = np.concatenate([np.arange(6 * problem.index[f], 6 * problem.index[f] + 6)
                           for f in keep_frames])
    Hmm = H[np.ix_(marg, marg)]
    H_km = H[np.ix_(keep, marg)]
    H_exp = H[np.ix_(keep, keep)] - H_km @ np.linalg.solve(Hmm, H_km.T)
    b_exp = b[keep] - H_km @ np.linalg.solve(Hmm, b[marg])

    report = win.marginalize([f0])
    assert report.marginalized_frames == (f0,)
    assert set(report.removed_landmarks) == set(hosted)
    assert win.prior.frame_ids == keep_frames
    scale = np.abs(H_exp).max()
    np.testing.assert_allclose(win.prior.H, H_exp, atol=2e-6 * scale)
    # new prior states are linearised at the current estimate, so b_m is the gradient there
    np.testing.assert_allclose(win.prior.b, b_exp, atol=2e-6 * np.abs(b_exp).max())


def test_prior_null_space_is_the_monocular_gauge_and_survives_relinearisation():
    """Without gauge prior and scale fix the prior has exactly the 7-dim null space (6 pose + scale)
    spanned by the analytic gauge directions at its linearisation points; first-estimate
    Jacobians keep it when more states are marginalised after the estimate moved."""
    scene = _scene(seed=4)
    win = build_window(scene, BackendConfig(initial_pose_weight=0.0, **LSQ),
                       pose_noise=(0.01, 0.005), bearing_noise=0.001, inv_dist_noise=0.1)
    f = scene.frame_ids
    win.marginalize([f[0]])
    assert len(win.prior.frame_ids) >= 3
    H = win.prior.H
    assert _null_dim(H) == 7
    N = _gauge_vectors([win.prior.lin_poses[g] for g in win.prior.frame_ids])
    assert np.linalg.matrix_rank(N) == 7
    assert np.abs(H @ N).max() < 1e-9 * np.abs(H).max() * np.abs(N).max()
    # move every state (as optimisation would), then marginalise the next keyframe
    rng = np.random.default_rng(5)
    for g in win.frame_ids:
        xi = np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.01, 3)]
        win.set_pose(g, decoupled_increment(win.pose(g), xi))
    win.marginalize([f[1]])
    assert _null_dim(win.prior.H) == 7
    N = _gauge_vectors([win.prior.lin_poses[g] for g in win.prior.frame_ids])
    assert np.abs(win.prior.H @ N).max() < 1e-9 * np.abs(win.prior.H).max() * np.abs(N).max()


def test_prior_keeps_gauge_and_scale_information():
    """With the gauge prior and a scale fix on the marginalised keyframe, the remaining window
    is fully determined (no null space); without the scale fix exactly the scale is free."""
    for with_scale in (True, False):
        scene = _scene(seed=6)
        win = build_window(scene, BackendConfig(**LSQ), pose_noise=(0.01, 0.005),
                           inv_dist_noise=0.1, seed=7)
        f = scene.frame_ids
        if with_scale:
            win.set_scale_fix(f[0], f[1], _true_length(scene, f[0], f[1]))
        win.optimize(max_iterations=3)
        report = win.marginalize([f[0]])
        assert report.scale_fix_marginalized is with_scale
        assert win.scale_fix is None
        assert _null_dim(win.hessian_blocks().H) == (0 if with_scale else 1)


def _converged_pair(seed):
    """Two identical windows optimised to convergence (the full-problem optimum)."""
    scene = _scene(seed=seed, num_frames=6, num_points=200)
    cfg = BackendConfig(step_tolerance=1e-12, **LSQ)
    wins = []
    for _ in range(2):
        win = build_window(scene, cfg, pose_noise=(0.02, 0.01), bearing_noise=0.002,
                           inv_dist_noise=0.2, seed=seed + 1)
        f = scene.frame_ids
        win.set_scale_fix(f[1], f[2], _true_length(scene, f[1], f[2]))
        wins.append(win)
    return scene, wins


def test_marginalized_problem_keeps_the_full_optimum():
    scene, (full, marg) = _converged_pair(seed=10)
    full.optimize(max_iterations=40)
    marg.optimize(max_iterations=40)
    f = scene.frame_ids
    marg.marginalize([f[0]])
    # disturb every remaining state, then optimise with the prior only
    rng = np.random.default_rng(11)
    for g in marg.frame_ids:
        xi = np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.005, 3)]
        marg.set_pose(g, decoupled_increment(marg.pose(g), xi))
    for lm_id in marg.landmarks.landmark_ids:
        marg.landmarks.landmark(lm_id).inv_dist *= 1.1
    marg.optimize(max_iterations=40)
    for g in marg.frame_ids:
        np.testing.assert_allclose(pose_delta(marg.pose(g), full.pose(g)), 0.0, atol=1e-7)
    for lm_id in marg.landmarks.landmark_ids:
        a, b = marg.landmarks.landmark(lm_id), full.landmarks.landmark(lm_id)
        np.testing.assert_allclose(a.s, b.s, atol=1e-8)
        assert a.inv_dist == pytest.approx(b.inv_dist, abs=1e-8)


def test_early_marginalization_matches_full_problem_within_linearisation_error():
    """Marginalising after two Gauss-Newton steps from a perturbed start (before convergence)
    and optimising the rest gives the full-problem estimate up to a small fraction of its
    standard deviation (the prior is frozen at a non-optimal linearisation point)."""
    scene, (full, marg) = _converged_pair(seed=20)
    full.optimize(max_iterations=40)
    marg.optimize(max_iterations=2)
    f = scene.frame_ids
    marg.marginalize([f[0]])
    marg.optimize(max_iterations=40)
    H = full.hessian_blocks()
    sigma = np.sqrt(np.diag(np.linalg.inv(H.H)))
    for g in marg.frame_ids:
        err = pose_delta(marg.pose(g), full.pose(g))
        assert np.all(np.abs(err) < 0.02 * sigma[H.block(g)]), (g, err / sigma[H.block(g)])


def test_non_keyframes_leave_by_dropping_observations():
    scene = _scene(seed=30, keyframe_every=2)
    win = build_window(scene, pose_noise=(0.01, 0.005), inv_dist_noise=0.1, seed=31)
    win.optimize(max_iterations=2)
    nonkf = [g for g in win.frame_ids if not win.is_keyframe(g)][0]
    assert win.landmarks.observed_in(nonkf)
    H0, b0, ids0 = win.prior.H.copy(), win.prior.b.copy(), list(win.prior.frame_ids)
    n_lm = len(win.landmarks)
    report = win.marginalize([nonkf])
    assert report.removed_frames == (nonkf,) and report.marginalized_frames == ()
    assert nonkf not in win and not win.landmarks.observed_in(nonkf)
    assert len(win.landmarks) == n_lm
    assert win.prior.frame_ids == ids0
    np.testing.assert_array_equal(win.prior.H, H0)
    np.testing.assert_array_equal(win.prior.b, b0)


def test_prior_is_never_relinearised():
    scene = _scene(seed=40)
    win = build_window(scene, pose_noise=(0.01, 0.005), inv_dist_noise=0.1, seed=41)
    win.marginalize([scene.frame_ids[0]])
    lin = {g: T.copy() for g, T in win.prior.lin_poses.items()}
    win.optimize()
    for g, T in win.prior.lin_poses.items():
        np.testing.assert_array_equal(T, lin[g])
    assert any(not np.array_equal(win.pose(g), lin[g]) for g in lin)


def test_incremental_sliding_window_tracks_truth():
    """Frames arrive one by one; keyframes host new landmarks; the window is kept at its size
    by the policy. The final window stays close to the truth and bounded in size."""
    scene = make_scene(num_frames=20, num_points=500, sigma=0.5, keyframe_every=2,
                       obs_per_landmark=6, seed=60)
    cfg = BackendConfig(max_frames=3, max_keyframes=5)
    win = SlidingWindow(scene.camera, cfg)
    by_frame: dict[int, list] = {}
    for obs in scene.observations:
        by_frame.setdefault(obs[1], []).append(obs)
    lm_index = {lm: i for i, lm in enumerate(scene.lm_ids)}
    rng = np.random.default_rng(61)
    for k, fid in enumerate(scene.frame_ids):
        guess = scene.poses[0] if k == 0 else decoupled_increment(
            win.pose(win.frame_ids[-1]) @ np.linalg.inv(scene.poses[k - 1]) @ scene.poses[k],
            np.r_[rng.normal(0, 0.005, 3), rng.normal(0, 0.002, 3)])
        win.add_frame(fid, guess, is_keyframe=scene.keyframe[k])
        for lm, f, uv, lvl in by_frame.get(fid, []):
            if lm not in win.landmarks:
                if scene.lm_host[lm_index[lm]] != fid:
                    continue  # host already left the window
                i = lm_index[lm]
                win.add_landmark(lm, fid, scene.lm_bearing[i],
                                 scene.lm_inv_dist[i] * (1 + rng.normal(0, 0.1)))
            win.add_observation(lm, fid, uv, lvl)
        if k == 2:
            win.set_scale_fix(scene.frame_ids[0], fid,
                              _true_length(scene, scene.frame_ids[0], fid))
        start = win.hessian_blocks()  # the system at the estimate the optimisation starts from
        report = win.optimize(snapshot_iteration=0)
        assert np.isfinite(report.final_cost)
        snap = report.snapshot
        assert snap is not None and snap.cost == report.costs[0]
        assert snap.cost == pytest.approx(start.cost, rel=1e-12)
        if k >= 2:  # gauge and scale fixed: entropy of the newest pose from the dense covariance
            blk = start.block(fid)
            cov = np.linalg.inv(start.H)[blk, blk]
            assert snap.negative_entropy(fid) == pytest.approx(-np.linalg.slogdet(cov)[1],
                                                               rel=1e-6)
        win.remove_outliers()
        win.marginalize(frames_to_marginalize(win, cfg))
        assert len(win.frame_ids) <= cfg.max_frames + cfg.max_keyframes
        assert set(win.prior.frame_ids) <= set(win.frame_ids)
    for fid in win.frame_ids:
        err = pose_delta(win.pose(fid), scene.pose_of(fid))
        assert np.linalg.norm(err[:3]) < 0.1 and np.degrees(np.linalg.norm(err[3:])) < 0.5
    assert isinstance(win.prior, MargPrior) and len(win.prior.frame_ids) > 0


def _kf_window(seed):
    scene = _scene(seed=seed, num_frames=7)
    win = build_window(scene, BackendConfig(**LSQ), pose_noise=(0.01, 0.005),
                       inv_dist_noise=0.1, seed=seed + 1)
    kfs = [f for f, k in zip(scene.frame_ids, scene.keyframe) if k]
    assert len(kfs) >= 4
    return scene, win, kfs


def test_marginalising_a_keyframe_outside_the_prior_keeps_the_prior():
    """The new prior replaces the old one, so it must carry the old one's information (here the
    gauge prior of the first frame) even when the marginalised keyframe is not one of its
    states."""
    scene, win, kfs = _kf_window(8)
    win.set_scale_fix(kfs[0], kfs[1], _true_length(scene, kfs[0], kfs[1]))
    win.optimize(max_iterations=3)
    assert _null_dim(win.hessian_blocks().H) == 0
    report = win.marginalize([kfs[2]])
    assert report.marginalized_frames == (kfs[2],)
    assert kfs[0] in win.prior.frame_ids
    assert _null_dim(win.hessian_blocks().H) == 0


def test_scale_fix_leaving_without_links_is_anchored_again():
    """A scale-fix frame whose landmarks are gone takes the scale with it when marginalised (its
    distance to the other frame constrains nothing left); the window then fixes the scale again
    at its current value instead of leaving it free."""
    scene, win, kfs = _kf_window(9)
    lonely = kfs[1]
    db = win.landmarks
    for lm in list(db.hosted_by(lonely)):
        db.remove_landmark(lm)
    for lm in list(db.observed_in(lonely)):
        db.remove_observation(lm, lonely)
    win.set_scale_fix(kfs[0], lonely, _true_length(scene, kfs[0], lonely))
    win.optimize(max_iterations=3)
    lengths = {f: win.pose(f)[:3, 3] for f in win.keyframe_ids}
    report = win.marginalize([lonely])
    assert report.scale_fix_marginalized
    sf = win.scale_fix
    assert sf is not None and lonely not in (sf.frame_i, sf.frame_j)
    assert sf.length == pytest.approx(float(np.linalg.norm(lengths[sf.frame_i] - lengths[sf.frame_j])))
    assert _null_dim(win.hessian_blocks().H) == 0
