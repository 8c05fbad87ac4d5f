"""Gauss-Newton steps that reuse a linearisation (``[backend] jacobian_reuse_steps``): the
gradient of such a step against a dense computation, and the optimisation with reuse against
the one without on noisy synthetic windows."""

from __future__ import annotations

import numpy as np
import pytest

from granite.backend import BackendConfig, pose_delta
from granite.backend.linearization import WindowCost
from granite.backend.reprojection import linearize, residuals_at
from granite.backend.schur import reduced_gradient, schur_reduce
from granite.backend import solver
from granite.backend.solver import predicted_decrease
from granite.backend.synthetic import build_window, make_scene
from granite.geometry import decoupled_increment

NO_HUBER = BackendConfig(huber_threshold=1e6)


def _skew(d):
    return np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])


def _dense_jacobian(K, pk, lin):
    """The (2N, 6K + 3M) Jacobian assembled from the per-observation blocks: host columns
    ``J_h``, target columns ``J_h M`` with ``M = [[-I, [t_h - t_t]x], [0, -I]]``, landmark
    columns ``J_l`` (observations in their host: landmark columns only)."""
    N, M = pk.num_observations, pk.num_landmarks
    J = np.zeros((2 * N, 6 * K + 3 * M))
    for k in range(N):
        i = pk.obs_lm[k]
        h, t = pk.lm_host[i], pk.obs_tgt[k]
        rows = slice(2 * k, 2 * k + 2)
        J[rows, 6 * K + 3 * i:6 * K + 3 * i + 3] = lin.J_l[k]
        if h == t:
            continue
        Mt = -np.eye(6)
        Mt[:3, 3:] = _skew(lin.t_lin[h] - lin.t_lin[t])
        J[rows, 6 * h:6 * h + 6] += lin.J_h[k]
        J[rows, 6 * t:6 * t + 6] += lin.J_h[k] @ Mt
    return J


def _window(config=None, seed=0):
    scene = make_scene(num_frames=6, num_points=60, sigma=0.5, seed=seed)
    win = build_window(scene, config, pose_noise=(0.02, 0.01), bearing_noise=0.003,
                       inv_dist_noise=0.3, seed=seed + 1)
    return scene, win


def test_reused_gradient_matches_a_dense_computation():
    """Jacobians and Hessian weights of one state, residuals and robust weights of another
    (the Huber weights differ): ``b_red = g_P - H_PL H_LL^-1 g_L`` with ``H = J^T W_old J``
    and ``g = J^T W_new r_new``, computed densely."""
    cfg = BackendConfig(huber_threshold=0.7, landmark_damping=0.0)
    _, win = _window(cfg)
    problem = win.problem()
    pk = problem.packed
    K = len(problem.frame_ids)
    inv_var = 1.0 / cfg.obs_std_dev ** 2
    lin = linearize(win.camera, pk, problem.poses, problem.poses, inv_var,
                    cfg.huber_threshold, cfg.infinite_obs_factor)
    J_h, J_l, w_old = lin.J_h.copy(), lin.J_l.copy(), lin.w.copy()
    red = schur_reduce(K, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r, w_old, J_h, J_l,
                       lin.t_lin, 0.0, 0.0)
    # another state: every pose moved a little
    rng = np.random.default_rng(5)
    moved = np.stack([decoupled_increment(np.ascontiguousarray(T), rng.normal(size=6) * 2e-3)
                      for T in problem.poses])
    r, w, valid, cost = residuals_at(win.camera, pk, moved, inv_var, cfg.huber_threshold,
                                     cfg.infinite_obs_factor)
    assert valid.all() and not np.allclose(w, w_old)
    # the residuals and cost are those of a full linearisation at that state
    full = linearize(win.camera, pk, moved, moved, inv_var, cfg.huber_threshold,
                     cfg.infinite_obs_factor)
    np.testing.assert_array_equal(r, full.r)
    np.testing.assert_array_equal(w, full.w)
    assert cost == full.cost
    b_raw, b_red, b_l = reduced_gradient(K, pk.lm_ptr, pk.lm_host, pk.obs_tgt, r, w, w_old,
                                         J_h, J_l, lin.t_lin, red[4])
    J = _dense_jacobian(K, pk, lin)
    H = J.T @ (np.repeat(w_old, 2)[:, None] * J)
    g = J.T @ (np.repeat(w, 2) * r.reshape(-1))
    P, L = slice(0, 6 * K), slice(6 * K, None)
    scale = np.abs(g).max()
    np.testing.assert_allclose(b_raw, g[P], atol=1e-10 * scale)
    np.testing.assert_allclose(b_l.reshape(-1), g[L], atol=1e-10 * scale)
    expected = g[P] - H[P, L] @ np.linalg.solve(H[L, L], g[L])
    np.testing.assert_allclose(b_red, expected, atol=1e-7 * scale)


def test_reused_gradient_with_the_same_residuals_is_the_elimination_gradient():
    _, win = _window(BackendConfig())
    problem = win.problem()
    pk = problem.packed
    K = len(problem.frame_ids)
    lin = linearize(win.camera, pk, problem.poses, problem.poses, 4.0, 1.0, 0.01)
    _, b, _, b_red, Hll_inv, b_l = schur_reduce(K, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r,
                                                lin.w, lin.J_h, lin.J_l, lin.t_lin, 1e-9, 0.0)
    got = reduced_gradient(K, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r, lin.w, lin.w,
                           lin.J_h, lin.J_l, lin.t_lin, Hll_inv)
    for a, e in zip(got, (b, b_red, b_l)):
        np.testing.assert_allclose(a, e, rtol=0.0, atol=1e-12 * np.abs(e).max())


@pytest.fixture
def no_step_gate(monkeypatch):
    """Reuse also far from the tolerance (these tests stop at 1e-9, where the step gate would
    allow reuse only in the last steps)."""
    monkeypatch.setattr(solver, "REUSE_MAX_STEP", 1e12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_optimisation_with_reuse_reaches_the_same_optimum_with_fewer_linearisations(
        seed, no_step_gate):
    """The fixed point of the reused steps is where the gradient through the reused Jacobians
    vanishes; re-linearising every few steps brings it to the optimum of the plain
    Gauss-Newton iteration: poses within 1e-6 of each other (the pose errors against the
    truth are about 1e-3), far fewer linearisations."""
    scene = make_scene(num_frames=8, num_points=200, sigma=0.5, seed=seed)
    ends = {}
    for reuse in (0, 3):
        cfg = BackendConfig(jacobian_reuse_steps=reuse, step_tolerance=1e-9)
        win = build_window(scene, cfg, pose_noise=(0.03, 0.01), bearing_noise=0.003,
                           inv_dist_noise=0.3, seed=seed + 10)
        fi, fj = scene.frame_ids[:2]
        win.set_scale_fix(fi, fj, float(np.linalg.norm(scene.pose_of(fi)[:3, 3]
                                                       - scene.pose_of(fj)[:3, 3])))
        report = win.optimize(max_iterations=40)
        assert report.converged and not report.reverted
        ends[reuse] = (report, np.stack([win.pose(f) for f in scene.frame_ids]))
    (plain, poses0), (reused, poses3) = ends[0], ends[3]
    assert plain.linearizations == plain.iterations
    assert reused.linearizations < plain.linearizations
    for T0, T3 in zip(poses0, poses3):
        assert np.max(np.abs(pose_delta(T3, T0))) < 1e-6
    # the first pose is held by the gauge prior; the others are off the truth by the noise
    errors = [np.max(np.abs(pose_delta(T0, scene.pose_of(f))))
              for T0, f in zip(poses0[1:], scene.frame_ids[1:])]
    assert max(errors) > 1e-4
    assert abs(reused.final_cost - plain.final_cost) <= 1e-9 * plain.final_cost


def test_a_reused_step_that_raises_the_cost_is_undone_and_linearised_again(no_step_gate):
    """A reused step that raises the cost (here its gradient is spoiled on purpose) is undone
    and the next step linearises again; Levenberg-Marquardt does not take over (that is for
    failed steps of a fresh linearisation)."""
    scene, win = _window(BackendConfig(jacobian_reuse_steps=2))
    calls = []
    original = WindowCost.regradient

    def spoiled(self, problem, lin, red):
        out_lin, out_red = original(self, problem, lin, red)
        calls.append(1)
        return out_lin, out_red._replace(b=out_red.b * 50.0)

    WindowCost.regradient = spoiled
    try:
        report = win.optimize(max_iterations=9)
    finally:
        WindowCost.regradient = original
    assert calls
    assert not report.reverted and win._solver_state.lm_calls_left == 0
    assert report.linearizations > 1
    # every accepted state's cost is at most the previous one
    assert all(b <= a * (1 + 1e-9) for a, b in zip(report.costs, report.costs[1:]))
    assert report.final_cost <= min(report.costs) * (1 + 1e-9)


def test_predicted_decrease_is_that_of_the_dense_quadratic_model():
    """``predicted_decrease`` from the reduced system equals ``E - min of the model``
    ``E + 2 g^T d + d^T H d`` over poses and landmarks, computed densely."""
    cfg = BackendConfig(huber_threshold=1e6, landmark_damping=0.0)
    _, win = _window(cfg)
    problem = win.problem()
    pk = problem.packed
    K = len(problem.frame_ids)
    lin = linearize(win.camera, pk, problem.poses, problem.poses, 4.0, 1e6, 1.0)
    _, _, H_red, b_red, Hll_inv, b_l = schur_reduce(K, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r,
                                                   lin.w, lin.J_h, lin.J_l, lin.t_lin, 0.0, 0.0)
    H_red = H_red + 1e8 * np.eye(6 * K) * (np.arange(6 * K) < 6)  # hold the first pose
    dx = np.linalg.solve(H_red, -b_red)
    J = _dense_jacobian(K, pk, lin)
    H = J.T @ (np.repeat(lin.w, 2)[:, None] * J)
    g = J.T @ (np.repeat(lin.w, 2) * lin.r.reshape(-1))
    H[:6, :6] += 1e8 * np.eye(6)
    step = np.linalg.solve(H, -g)
    expected = -(2.0 * g @ step + step @ H @ step)
    got = predicted_decrease(b_red, dx, b_l, Hll_inv)
    assert got > 0.0
    assert got == pytest.approx(expected, rel=1e-6)
    assert -float(b_red @ dx) < 0.9 * expected  # the landmark term matters


def test_far_from_the_optimum_the_linearisations_are_not_reused(no_step_gate):
    """Large pose and depth errors: the first steps' cost decreases differ from their models'
    predictions by more than ``REUSE_GAIN_TOLERANCE``, so those linearisations are not reused
    (the first three costs are those of plain Gauss-Newton, to the bit); both runs end at
    the same optimum."""
    scene = make_scene(num_frames=8, num_points=200, sigma=0.5, seed=4)
    fi, fj = scene.frame_ids[:2]
    ends = {}
    for reuse in (0, 3):
        cfg = BackendConfig(jacobian_reuse_steps=reuse, step_tolerance=1e-8)
        win = build_window(scene, cfg, pose_noise=(0.1, 0.04), bearing_noise=0.005,
                           inv_dist_noise=1.0, seed=7)
        win.set_scale_fix(fi, fj, float(np.linalg.norm(scene.pose_of(fi)[:3, 3]
                                                       - scene.pose_of(fj)[:3, 3])))
        report = win.optimize(max_iterations=60)
        assert report.converged and not report.reverted
        ends[reuse] = (report, np.stack([win.pose(f) for f in scene.frame_ids]))
    plain, reused = ends[0][0], ends[3][0]
    assert plain.costs[0] > 100.0 * plain.final_cost  # far from the optimum
    assert reused.costs[:3] == plain.costs[:3]
    assert reused.linearizations < reused.iterations
    for T0, T3 in zip(ends[0][1], ends[3][1]):
        assert np.max(np.abs(pose_delta(T3, T0))) < 1e-6

