"""Backend derivatives against finite differences and dense, independently assembled systems."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend import BackendConfig
from granite.backend.stereographic import (
    bearing_from_stereo,
    bearings_from_stereo,
    stereo_from_bearing,
)
from granite.backend.priors import ScaleFix, no_motion_terms
from granite.backend.reprojection import linearize, reprojection_residuals
from granite.backend.schur import back_substitute, relative_map, schur_reduce
from granite.backend.synthetic import build_window, make_scene
from granite.camera import make_camera
from granite.geometry import decoupled_increment

CAMERAS = {
    "pinhole": ("pinhole", {"fx": 500.0, "fy": 480.0, "cx": 319.5, "cy": 239.5}),
    "kb4": ("kb4", {"fx": 380.0, "fy": 381.0, "cx": 320.0, "cy": 240.0,
                    "k1": 0.01, "k2": -0.005, "k3": 0.002, "k4": -0.0005}),
    "ds": ("ds", {"fx": 350.0, "fy": 352.0, "cx": 321.0, "cy": 239.0,
                  "xi": -0.2, "alpha": 0.6}),
}


def _window(camera_name: str = "pinhole", seed: int = 0, **kw):
    scene = make_scene(num_frames=4, num_points=25, seed=seed)
    if camera_name != "pinhole":
        # re-observe the same geometry through another model (pixels from projection)
        scene.camera = make_camera(*CAMERAS[camera_name], 640, 480)
    win = build_window(scene, kw.pop("config", None), pose_noise=(0.02, 0.01),
                       bearing_noise=0.003, inv_dist_noise=0.3, seed=seed + 1)
    return scene, win


def _perturbed(poses, idx, c, eps):
    xi = np.zeros(6)
    xi[c] = eps
    out = poses.copy()
    out[idx] = decoupled_increment(np.ascontiguousarray(poses[idx]), xi)
    return out


def test_stereographic_roundtrip_and_jacobian():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(50, 3))
    b[:, 2] = np.abs(b[:, 2]) - 0.5  # include bearings pointing sideways/backwards
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    s = stereo_from_bearing(b)
    np.testing.assert_allclose(bearings_from_stereo(s), b, atol=1e-12)
    eps = 1e-6
    for si in s[:10]:
        _, J = bearing_from_stereo(si)
        for c in range(2):
            d = np.zeros(2)
            d[c] = eps
            num = (bearing_from_stereo(si + d)[0] - bearing_from_stereo(si - d)[0]) / (2 * eps)
            np.testing.assert_allclose(J[:, c], num, atol=1e-8)


@pytest.mark.parametrize("camera_name", ["pinhole", "kb4", "ds"])
def test_reprojection_jacobians_match_finite_differences(camera_name):
    _, win = _window(camera_name)
    problem = win.problem()
    pk = problem.packed
    # one point at infinity: its inverse-distance column must be zero, pose rotations still act
    pk.lm_d[3] = 0.0
    lin = linearize(win.camera, pk, problem.poses, problem.poses, 1.0, 1e9, 1.0)
    assert np.all(lin.valid)
    eps = 1e-6
    K = len(problem.frame_ids)
    num_pose = np.zeros((pk.num_observations, 2, K, 6))
    for idx in range(K):
        for c in range(6):
            rp, _ = reprojection_residuals(win.camera, pk, _perturbed(problem.poses, idx, c, eps))
            rm, _ = reprojection_residuals(win.camera, pk, _perturbed(problem.poses, idx, c, -eps))
            num_pose[:, :, idx, c] = (rp - rm) / (2 * eps)
    host = pk.lm_host[pk.obs_lm]
    for k in range(pk.num_observations):
        h, t = host[k], pk.obs_tgt[k]
        if h == t:
            assert np.all(lin.J_h[k] == 0)
            continue
        scale = np.abs(num_pose[k]).max() + 1.0
        np.testing.assert_allclose(lin.J_h[k], num_pose[k, :, h], atol=1e-5 * scale)
        # the target's Jacobian is the host's times the relative map of the two centres
        J_t = lin.J_h[k] @ relative_map(lin.t_lin[h], lin.t_lin[t])
        np.testing.assert_allclose(J_t, num_pose[k, :, t], atol=1e-5 * scale)
    s0, d0 = pk.lm_s.copy(), pk.lm_d.copy()
    for c in range(3):
        rs = []
        for sign in (1, -1):
            pk.lm_s[:], pk.lm_d[:] = s0, d0
            if c < 2:
                pk.lm_s[:, c] += sign * eps
            else:
                pk.lm_d[:] += sign * eps
            rs.append(reprojection_residuals(win.camera, pk, problem.poses)[0])
        num = (rs[0] - rs[1]) / (2 * eps)
        pk.lm_s[:], pk.lm_d[:] = s0, d0
        for k in range(pk.num_observations):
            if c == 2 and pk.obs_lm[k] == 3:
                assert np.all(lin.J_l[k, :, 2] == 0.0)  # d = 0 stays at infinity
                continue
            np.testing.assert_allclose(lin.J_l[k, :, c], num[k],
                                       atol=1e-5 * (np.abs(num[k]).max() + 1))
    # at d = 0 the translation does not act on the residual
    inf_obs = np.flatnonzero((pk.obs_lm == 3) & (host != pk.obs_tgt))
    assert inf_obs.size > 0
    assert np.all(lin.J_h[inf_obs][:, :, :3] == 0)


def test_first_estimate_jacobians_use_linearisation_poses():
    _, win = _window()
    problem = win.problem()
    pk = problem.packed
    poses_lin = problem.poses.copy()
    moved = problem.poses.copy()
    moved[1] = decoupled_increment(moved[1], np.array([0.01, -0.02, 0.01, 0.003, 0.0, -0.002]))
    at_lin = linearize(win.camera, pk, poses_lin, poses_lin, 4.0, 1e9, 1.0)
    J_h, J_l = at_lin.J_h.copy(), at_lin.J_l.copy()
    fej = linearize(win.camera, pk, moved, poses_lin, 4.0, 1e9, 1.0)
    np.testing.assert_array_equal(fej.J_h, J_h)
    np.testing.assert_array_equal(fej.t_lin, poses_lin[:, :3, 3])
    np.testing.assert_array_equal(fej.J_l, J_l)
    res, _ = reprojection_residuals(win.camera, pk, moved)
    np.testing.assert_allclose(fej.r, res, atol=1e-12)


@pytest.mark.parametrize("camera_name", ["pinhole", "kb4", "ds"])
def test_linearisation_validity_follows_the_camera_projection(camera_name):
    """Observations whose point does not project (behind the camera) at the estimate or at the
    linearisation point get weight 0 and zero rows; the others the camera's own pixels."""
    _, win = _window(camera_name)
    problem = win.problem()
    pk = problem.packed
    poses_lin = problem.poses.copy()
    moved = problem.poses.copy()
    # turn frame 1 half around at the estimate, frame 2 at the linearisation point
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    moved[1] = moved[1] @ flip
    poses_lin[2] = poses_lin[2] @ flip
    lin = linearize(win.camera, pk, moved, poses_lin, 4.0, 1e9, 1.0)

    def points(poses):
        out = np.empty((pk.num_observations, 3))
        for k in range(pk.num_observations):
            i, t = pk.obs_lm[k], pk.obs_tgt[k]
            h = pk.lm_host[i]
            b = bearings_from_stereo(pk.lm_s[i])
            if h == t:
                out[k] = b
            else:
                T_t_h = np.linalg.inv(poses[t]) @ poses[h]
                out[k] = T_t_h[:3, :3] @ b + T_t_h[:3, 3] * pk.lm_d[i]
        return out

    uv, valid_res = win.camera.project(points(moved))
    _, _, _, valid_lin = win.camera.project_jacobians(points(poses_lin))
    expected = valid_res & valid_lin
    assert 0 < expected.sum() < len(expected)  # both kinds occur
    np.testing.assert_array_equal(lin.valid, expected)
    assert np.all(lin.w[~expected] == 0.0)
    for J in (lin.r, lin.J_h, lin.J_l):
        assert np.all(J[~expected] == 0.0)
    np.testing.assert_allclose(lin.r[expected], (uv - pk.obs_uv)[expected], atol=1e-9)


def _dense_problem(win):
    """Dense Jacobian (finite differences) of all weighted residuals over [poses, landmarks]."""
    problem = win.problem()
    pk = problem.packed
    K, M, N = len(problem.frame_ids), pk.num_landmarks, pk.num_observations
    eps = 1e-6

    def residuals(poses, s, d):
        pk.lm_s[:], pk.lm_d[:] = s, d
        return reprojection_residuals(win.camera, pk, poses)[0].reshape(-1)

    s0, d0 = pk.lm_s.copy(), pk.lm_d.copy()
    J = np.zeros((2 * N, 6 * K + 3 * M))
    for idx in range(K):
        for c in range(6):
            J[:, 6 * idx + c] = (residuals(_perturbed(problem.poses, idx, c, eps), s0, d0)
                                 - residuals(_perturbed(problem.poses, idx, c, -eps), s0, d0)
                                 ) / (2 * eps)
    for i in range(M):
        for c in range(3):
            sp, sm, dp, dm = s0.copy(), s0.copy(), d0.copy(), d0.copy()
            if c < 2:
                sp[i, c] += eps
                sm[i, c] -= eps
            else:
                dp[i] += eps
                dm[i] -= eps
            J[:, 6 * K + 3 * i + c] = (residuals(problem.poses, sp, dp)
                                       - residuals(problem.poses, sm, dm)) / (2 * eps)
    r = residuals(problem.poses, s0, d0)
    cfg = win.config
    w = np.repeat(2.0 ** -pk.obs_level / cfg.obs_std_dev ** 2, 2)
    return problem, J, r, w


def test_schur_complement_matches_dense_normal_equations():
    _, win = _window(config=BackendConfig(huber_threshold=1e6, landmark_damping=0.0))
    problem, J, r, w = _dense_problem(win)
    pk = problem.packed
    K = len(problem.frame_ids)
    H = J.T @ (w[:, None] * J)
    b = J.T @ (w * r)
    lin = linearize(win.camera, pk, problem.poses, problem.poses, 1.0 / 0.25, 1e6, 1.0)
    H_raw, b_raw, H_red, b_red, Hll_inv, b_l = schur_reduce(
        K, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r, lin.w, lin.J_h, lin.J_l, lin.t_lin, 0.0, 0.0)
    P = slice(0, 6 * K)
    L = slice(6 * K, None)
    scale = np.abs(H).max()
    np.testing.assert_allclose(H_raw, H[P, P], atol=1e-6 * scale)
    np.testing.assert_allclose(b_raw, b[P], atol=1e-6 * np.abs(b).max())
    H_schur = H[P, P] - H[P, L] @ np.linalg.solve(H[L, L], H[L, P])
    b_schur = b[P] - H[P, L] @ np.linalg.solve(H[L, L], b[L])
    np.testing.assert_allclose(H_red, H_schur, atol=1e-6 * scale)
    np.testing.assert_allclose(b_red, b_schur, atol=1e-6 * np.abs(b).max())
    np.testing.assert_allclose(b_l.reshape(-1), b[L], atol=1e-6 * np.abs(b).max())
    # back-substitution: the landmark part of the full Newton step for a given pose step
    dx = np.random.default_rng(3).normal(size=6 * K) * 1e-3
    dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h, lin.J_l,
                         lin.t_lin, Hll_inv, b_l)
    expected = -np.linalg.solve(H[L, L], b[L] + H[L, P] @ dx)
    np.testing.assert_allclose(dl.reshape(-1), expected, rtol=1e-5, atol=1e-9)


def test_scale_fix_and_no_motion_derivatives():
    rng = np.random.default_rng(1)
    Ti = decoupled_increment(np.eye(4), rng.normal(size=6))
    Tj = decoupled_increment(np.eye(4), rng.normal(size=6))
    sf = ScaleFix(1, 2, 0.7, 3.0)
    terms = [lambda a, b: sf.linearize(a, b), lambda a, b: no_motion_terms(a, b, 2.5)]
    eps = 1e-6
    for term in terms:
        H, b, cost = term(Ti, Tj)
        grad = np.zeros(12)
        for which in range(2):
            for c in range(6):
                xi = np.zeros(6)
                xi[c] = eps
                args_p = [Ti, Tj]
                args_m = [Ti, Tj]
                args_p[which] = decoupled_increment(args_p[which], xi)
                args_m[which] = decoupled_increment(args_m[which], -xi)
                grad[6 * which + c] = (term(*args_p)[2] - term(*args_m)[2]) / (2 * eps)
        np.testing.assert_allclose(2 * b, grad, atol=1e-6)
        assert np.allclose(H, H.T) and np.min(np.linalg.eigvalsh(H)) > -1e-9


def test_window_gradient_matches_robust_cost():
    """Total gradient (reprojection with active Huber weights + gauge prior + scale fix + no
    motion prior) against finite differences of :meth:`SlidingWindow.cost`."""
    scene, win = _window(config=BackendConfig(huber_threshold=0.4, no_motion_weight=0.5))
    win.set_scale_fix(scene.frame_ids[0], scene.frame_ids[2], 0.3)
    # all landmarks of one host at infinity: its pairs are linked only by d = 0 points
    for lm in win.landmarks.hosted_by(scene.frame_ids[-2]):
        win.set_inverse_distance(lm, 0.0)
    hess = win.hessian_blocks()
    assert np.any(hess.H_no_motion != 0) and np.any(hess.H_scale_fix != 0)
    # The window scatters the no-motion terms of all pairs at once: same as term by term.
    problem = win.problem()
    expected = np.zeros_like(hess.H_no_motion)
    for h, t in problem.no_motion_pairs(win.config.no_motion_weight):
        fh, ft = problem.frame_ids[h], problem.frame_ids[t]
        H, _, _ = no_motion_terms(win.pose(fh), win.pose(ft), 0.5)
        rows = np.r_[6 * hess.index(fh):6 * hess.index(fh) + 6, 6 * hess.index(ft):6 * hess.index(ft) + 6]
        expected[np.ix_(rows, rows)] += H
    np.testing.assert_allclose(hess.H_no_motion, expected, rtol=0, atol=1e-15)
    g_pose = hess.b - hess.b_reprojection + hess.b_reprojection_raw
    eps = 1e-6
    for f in win.frame_ids[1:]:
        k = hess.index(f)
        T0 = win.pose(f)
        for c in range(6):
            xi = np.zeros(6)
            xi[c] = eps
            win.set_pose(f, decoupled_increment(T0, xi))
            cp = win.cost()
            win.set_pose(f, decoupled_increment(T0, -xi))
            cm = win.cost()
            win.set_pose(f, T0)
            num = (cp - cm) / (4 * eps)
            assert abs(num - g_pose[6 * k + c]) <= 1e-4 * (abs(num) + 1.0), (f, c, num)


def _ill_conditioned_landmarks(damping: float):
    """Random 2x6 / 2x3 observation Jacobians over 4 poses with pixel-like magnitudes: well
    conditioned landmarks, landmarks with a single observation outside the host (a rank-2
    block, near-singular with the damping: the case that made the normal-equation elimination
    indefinite on the 320x240 spiral) and landmarks with a nearly dependent inverse-distance
    column (condition ~1e7)."""
    rng = np.random.default_rng(7)
    K = 4
    t_lin = 3.0 * rng.normal(size=(K, 3))  # camera centres: the target Jacobians J_h M
    lm_ptr, lm_host, obs_tgt = [0], [], []
    J_h, J_l, r, w = [], [], [], []
    kinds = ["good"] * 6 + ["single"] * 6 + ["dependent"] * 4
    for kind in kinds:
        h = int(rng.integers(K))
        targets = [t for t in range(K) if t != h]
        if kind == "single":
            targets = [targets[int(rng.integers(len(targets)))]]
        cols = rng.normal(size=(2, 3))
        for t in [h] + targets:
            J_h.append(800.0 * rng.normal(size=(2, 6)) if t != h else np.zeros((2, 6)))
            jl = 800.0 * rng.normal(size=(2, 3))
            if kind == "dependent":  # inverse-distance column ~ parallel to the first one
                jl[:, 2] = 3.0 * jl[:, 0] + 1e-7 * 800.0 * rng.normal(size=2)
                jl[:, 1] = 800.0 * cols[:, 1] + rng.normal(size=2)
            J_l.append(jl)
            r.append(rng.normal(size=2))
            w.append(4.0 * 2.0 ** -int(rng.integers(3)))
            obs_tgt.append(t)
        if kind == "single":  # the host observation left out (e.g. an outlier)
            w[-2] = 0.0
        lm_host.append(h)
        lm_ptr.append(len(obs_tgt))
    arr = lambda x, dt=np.float64: np.ascontiguousarray(np.array(x, dtype=dt))  # noqa: E731
    return (K, arr(lm_ptr, np.int64), arr(lm_host, np.int64), arr(obs_tgt, np.int64), arr(r),
            arr(w), arr(J_h), arr(J_l), arr(t_lin), damping)


def _skew(d):
    return np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])


def _projected_reference(K, lm_ptr, lm_host, obs_tgt, r, w, J_h, J_l, t_lin, damping):
    """Reduced system by orthogonal projection with numpy's SVD (stable): per landmark
    ``A_p^T (I - U U^T) A_p`` with ``U`` the left singular vectors of the damped, weighted
    landmark Jacobian above a relative rank threshold; the absolute target Jacobian is
    ``J_h [[-I, [t_h - t_t]x], [0, -I]]``, written out here independently of the kernel."""
    H = np.zeros((6 * K, 6 * K))
    b = np.zeros(6 * K)
    for i in range(len(lm_host)):
        ks = [k for k in range(lm_ptr[i], lm_ptr[i + 1]) if w[k] > 0.0]
        h = lm_host[i]
        A_p = np.zeros((2 * len(ks) + 3, 6 * K))
        A_l = np.zeros((2 * len(ks) + 3, 3))
        rr = np.zeros(2 * len(ks) + 3)
        for row, k in enumerate(ks):
            s = np.sqrt(w[k])
            if obs_tgt[k] != h:
                t = obs_tgt[k]
                M = -np.eye(6)
                M[:3, 3:] = _skew(t_lin[h] - t_lin[t])
                A_p[2 * row:2 * row + 2, 6 * h:6 * h + 6] += s * J_h[k]
                A_p[2 * row:2 * row + 2, 6 * t:6 * t + 6] += s * J_h[k] @ M
            A_l[2 * row:2 * row + 2] = s * J_l[k]
            rr[2 * row:2 * row + 2] = s * r[k]
        A_l[2 * len(ks):] = np.sqrt(damping) * np.eye(3)
        U, sv, _ = np.linalg.svd(A_l, full_matrices=False)
        U = U[:, sv > 1e-12 * sv.max()]
        P = np.eye(len(A_l)) - U @ U.T
        H += A_p.T @ P @ A_p
        b += A_p.T @ P @ rr
    return H, b


def test_schur_reduce_without_rhs_gives_the_same_matrices():
    _, win = _window("kb4", seed=3)
    problem = win.problem()
    pk = problem.packed
    lin = linearize(win.camera, pk, problem.poses, problem.poses, 4.0, 1.0, 1.0)
    args = (len(problem.frame_ids), pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r, lin.w, lin.J_h,
            lin.J_l, lin.t_lin, 1e-9, 0.0)
    full = schur_reduce(*args)
    mats = schur_reduce(*args, False)
    assert np.any(full[2] != 0.0) and np.any(full[3] != 0.0)
    np.testing.assert_array_equal(mats[0], full[0])
    np.testing.assert_array_equal(mats[2], full[2])
    for rhs in (mats[1], mats[3], mats[4], mats[5]):
        assert not np.any(rhs)


@pytest.mark.parametrize("damping", [1e-9, 0.0])
def test_schur_reduce_is_accurate_on_near_singular_landmark_blocks(damping):
    args = _ill_conditioned_landmarks(damping)
    H_raw, b_raw, H_red, b_red, Hll_inv, b_l = schur_reduce(*args, 0.0)
    H_ref, b_ref = _projected_reference(*args)
    scale = np.abs(H_raw).max()
    np.testing.assert_allclose(H_red, H_ref, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(b_red, b_ref, rtol=0, atol=1e-8 * np.abs(b_raw).max())
    assert np.linalg.eigvalsh(H_red)[0] >= -1e-12 * scale
    # the 3x3 inverses: exact for the well-conditioned landmarks
    K, lm_ptr, lm_host, obs_tgt, r, w, J_h, J_l, t_lin, _ = args
    for i in range(6):
        ks = [k for k in range(lm_ptr[i], lm_ptr[i + 1]) if w[k] > 0.0]
        Hll = sum(w[k] * J_l[k].T @ J_l[k] for k in ks) + damping * np.eye(3)
        np.testing.assert_allclose(Hll_inv[i] @ Hll, np.eye(3), atol=1e-9)


def test_no_motion_prior_determines_the_translations_above_round_off():
    """Paper Sec. IV-B: the no-motion prior ties the translations of frames linked only by
    points at infinity "avoiding an undetermined system". With every landmark at infinity
    nothing else informs the translations, so the window's pose system (gauge prior 1e8
    included) must be positive definite by more than its round-off (eps x lambda_max):
    the former default 1e-12 (and 1e-9) gave a smallest eigenvalue of round-off size and
    sign, and in the VO the translations wandered during a turn in place (docs/backend.md)."""
    _, win = _window()  # the default BackendConfig
    for f in win.frame_ids:
        for lm in win.landmarks.hosted_by(f):
            win.set_inverse_distance(lm, 0.0)
    hess = win.hessian_blocks()
    assert np.any(hess.H_no_motion != 0)
    lam = np.linalg.eigvalsh(0.5 * (hess.H + hess.H.T))
    assert lam[0] > 10 * np.finfo(float).eps * lam[-1]
