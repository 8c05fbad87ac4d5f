"""Tests of granite.geometry against independent computations (scipy, evo, explicit formulas)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
import scipy.linalg
from scipy.spatial.transform import Rotation, Slerp

from granite.geometry import (
    decoupled_increment,
    hat,
    interpolate_poses,
    quat_to_rotation,
    rotation_to_quat,
    se3_adjoint,
    se3_compose,
    se3_exp,
    se3_inverse,
    se3_log,
    sim3_exp,
    sim3_log,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
    umeyama_alignment,
    vee,
)

RNG_SEED = 20210927


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _rotvecs(rng: np.random.Generator) -> list[np.ndarray]:
    """Random rotation vectors plus edge cases: 0, tiny, around the series threshold, near pi."""
    out = [np.zeros(3)]
    for ang in [1e-15, 1e-10, 1e-7, 1e-4, 9.99e-4, 1.001e-3, 1e-2, 0.5, 1.0, 2.0, 3.0,
                np.pi - 1e-3, np.pi - 1e-6, np.pi - 1e-9]:
        out.append(ang * _unit(rng))
    for _ in range(30):
        out.append(rng.uniform(0.0, np.pi * 0.999) * _unit(rng))
    return out


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.uniform(0, 3.0) * _unit(rng)).as_matrix()
    T[:3, 3] = rng.normal(scale=3.0, size=3)
    return T


def _twist_matrix(xi: np.ndarray) -> np.ndarray:
    M = np.zeros((4, 4))
    M[:3, :3] = np.array([[0, -xi[5], xi[4]], [xi[5], 0, -xi[3]], [-xi[4], xi[3], 0]])
    M[:3, 3] = xi[:3]
    return M


# ----------------------------------------------------------------------------- SO(3)

def test_hat_vee():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(10):
        w = rng.normal(size=3)
        p = rng.normal(size=3)
        np.testing.assert_allclose(hat(w) @ p, np.cross(w, p), rtol=0, atol=1e-14)
        np.testing.assert_allclose(hat(w), -hat(w).T, atol=0)
        np.testing.assert_array_equal(vee(hat(w)), w)


def test_so3_exp_matches_scipy():
    rng = np.random.default_rng(RNG_SEED)
    for w in _rotvecs(rng):
        R = so3_exp(w)
        np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), rtol=0, atol=2e-15)
        np.testing.assert_allclose(R @ R.T, np.eye(3), rtol=0, atol=1e-15)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)


def test_so3_log_round_trip_and_edge_cases():
    rng = np.random.default_rng(RNG_SEED)
    for w in _rotvecs(rng):
        R = Rotation.from_rotvec(w).as_matrix()  # independent exponential
        w2 = so3_log(R)
        np.testing.assert_allclose(w2, w, rtol=0, atol=1e-12 + 1e-12 * np.linalg.norm(w))
    # tiny angles keep full relative precision
    w = np.array([1e-12, -2e-12, 3e-12])
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, rtol=1e-6, atol=0)
    # identity gives exactly zero
    np.testing.assert_array_equal(so3_log(np.eye(3)), np.zeros(3))


@pytest.mark.parametrize("axis", [np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                                  np.array([0, 0, 1.0]), np.array([1.0, -2.0, 0.5]) / np.sqrt(5.25)])
def test_so3_log_at_pi(axis):
    R = Rotation.from_rotvec(np.pi * axis).as_matrix()
    w = so3_log(R)
    assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-12)
    # +/- axis are both correct at exactly pi
    assert min(np.linalg.norm(w - np.pi * axis), np.linalg.norm(w + np.pi * axis)) < 1e-12
    np.testing.assert_allclose(Rotation.from_rotvec(w).as_matrix(), R, atol=1e-14)


def _num_jacobian(f, x: np.ndarray, h: float) -> np.ndarray:
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def test_so3_jacobians_central_differences():
    rng = np.random.default_rng(RNG_SEED)
    ws = [np.zeros(3), 1e-9 * _unit(rng), 5e-4 * _unit(rng), 2e-3 * _unit(rng)]
    ws += [rng.uniform(0.1, 3.0) * _unit(rng) for _ in range(10)]
    for w in ws:
        Rinv = Rotation.from_rotvec(w).inv()

        def right(d):
            return (Rinv * Rotation.from_rotvec(w + d)).as_rotvec()

        def left(d):
            return (Rotation.from_rotvec(w + d) * Rinv).as_rotvec()

        Jr_num = _num_jacobian(right, np.zeros(3), 1e-6)
        Jl_num = _num_jacobian(left, np.zeros(3), 1e-6)
        Jr = so3_right_jacobian(w)
        Jl = so3_left_jacobian(w)
        assert np.linalg.norm(Jr - Jr_num) / np.linalg.norm(Jr_num) < 1e-8
        assert np.linalg.norm(Jl - Jl_num) / np.linalg.norm(Jl_num) < 1e-8
        np.testing.assert_allclose(so3_right_jacobian_inv(w) @ Jr, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(so3_left_jacobian_inv(w) @ Jl, np.eye(3), atol=1e-12)
        # J_l(w) = R J_r(w)
        np.testing.assert_allclose(Jl, Rotation.from_rotvec(w).as_matrix() @ Jr, atol=1e-14)


# ----------------------------------------------------------------------------- SE(3)

def test_se3_exp_matches_expm_and_log_round_trip():
    rng = np.random.default_rng(RNG_SEED)
    for w in _rotvecs(rng):
        xi = np.concatenate([rng.normal(scale=2.0, size=3), w])
        T = se3_exp(xi)
        np.testing.assert_allclose(T, scipy.linalg.expm(_twist_matrix(xi)), rtol=0, atol=2e-13)
        tol = 1e-12 if np.linalg.norm(w) < 3.0 else 1e-8  # J_l^-1 grows near pi
        np.testing.assert_allclose(se3_log(T), xi, rtol=0, atol=tol)


def test_se3_inverse_compose_adjoint():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(20):
        A = _random_pose(rng)
        B = _random_pose(rng)
        np.testing.assert_allclose(se3_inverse(A), np.linalg.inv(A), atol=1e-13)
        np.testing.assert_allclose(se3_compose(A, B), A @ B, atol=1e-13)
        xi = np.concatenate([rng.normal(size=3), rng.uniform(0, 2.5) * _unit(rng)])
        lhs = A @ scipy.linalg.expm(_twist_matrix(xi)) @ np.linalg.inv(A)
        rhs = scipy.linalg.expm(_twist_matrix(se3_adjoint(A) @ xi))
        np.testing.assert_allclose(lhs, rhs, atol=1e-11)
        # block structure of paper Eq. 3
        Adj = se3_adjoint(A)
        R, t = A[:3, :3], A[:3, 3]
        np.testing.assert_allclose(Adj[:3, 3:], np.cross(t[:, None], R, axis=0), atol=1e-14)
        np.testing.assert_array_equal(Adj[3:, :3], np.zeros((3, 3)))


def test_decoupled_increment_eq14():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(10):
        T = _random_pose(rng)
        xi = np.concatenate([rng.normal(size=3), rng.uniform(0, 1.0) * _unit(rng)])
        out = decoupled_increment(T, xi)
        np.testing.assert_allclose(
            out[:3, :3], Rotation.from_rotvec(xi[3:]).as_matrix() @ T[:3, :3], atol=1e-14
        )
        np.testing.assert_allclose(out[:3, 3], T[:3, 3] + xi[:3], atol=1e-14)
        np.testing.assert_array_equal(out[3], [0, 0, 0, 1])
    # decoupled differs from the coupled left increment when rotating a translated pose
    T = np.eye(4)
    T[:3, 3] = [1.0, 0, 0]
    xi = np.array([0, 0, 0, 0, 0, 0.5])
    assert not np.allclose(decoupled_increment(T, xi), se3_exp(xi) @ T)


def test_kernels_reject_wrong_shapes():
    with pytest.raises(ValueError):
        se3_exp(np.zeros(5))
    with pytest.raises(ValueError):
        se3_inverse(np.eye(3))
    with pytest.raises(ValueError):
        hat(np.zeros(4))


# ----------------------------------------------------------------------------- Sim(3)

def _sim3_matrix(xi: np.ndarray) -> np.ndarray:
    M = _twist_matrix(xi[:6])
    M[:3, :3] += xi[6] * np.eye(3)
    return M


@pytest.mark.parametrize("sigma", [0.0, 1e-14, 1e-9, -1e-6, 1e-3, 0.3, -0.7, 1.999, 2.0, -2.5, 4.0])
def test_sim3_exp_log(sigma):
    rng = np.random.default_rng(RNG_SEED)
    for w in _rotvecs(rng)[:18]:
        xi = np.concatenate([rng.normal(size=3), w, [sigma]])
        S = sim3_exp(xi)
        S_ref = scipy.linalg.expm(_sim3_matrix(xi))
        np.testing.assert_allclose(S, S_ref, rtol=0, atol=1e-12 * max(1.0, np.abs(S_ref).max()))
        tol = 1e-11 if np.linalg.norm(w) < 3.0 else 1e-7
        np.testing.assert_allclose(sim3_log(S), xi, rtol=0, atol=tol)


def test_sim3_log_matches_logm():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(5):
        S = np.eye(4)
        S[:3, :3] = 1.7 * Rotation.from_rotvec(rng.uniform(0.1, 2.0) * _unit(rng)).as_matrix()
        S[:3, 3] = rng.normal(size=3)
        L = np.real(scipy.linalg.logm(S))
        xi_ref = np.concatenate([L[:3, 3], [L[2, 1], L[0, 2], L[1, 0]], [np.trace(L[:3, :3]) / 3]])
        np.testing.assert_allclose(sim3_log(S), xi_ref, atol=1e-10)
    with pytest.raises(ValueError):
        sim3_log(np.diag([-1.0, 1.0, 1.0, 1.0]))


# ----------------------------------------------------------------------------- quaternions

def test_quaternion_conversions_match_scipy():
    rng = np.random.default_rng(RNG_SEED)
    rots = Rotation.from_rotvec(np.array(_rotvecs(rng)))
    # add exact half-turns about each axis (qw = 0)
    rots = Rotation.concatenate([rots, Rotation.from_rotvec(np.pi * np.eye(3))])
    q_ref = rots.as_quat()  # xyzw
    q_ref *= np.where(q_ref[:, 3:4] < 0, -1, 1)
    R = rots.as_matrix()
    q = rotation_to_quat(R)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    # sign is ambiguous only when qw == 0
    err = np.minimum(np.linalg.norm(q - q_ref, axis=1), np.linalg.norm(q + q_ref, axis=1))
    assert err.max() < 1e-14
    np.testing.assert_allclose(quat_to_rotation(q_ref), R, atol=1e-15)
    # non-normalised input and batch shapes
    q2 = (3.0 * q_ref).reshape(-1, 1, 4)
    assert quat_to_rotation(q2).shape == (q_ref.shape[0], 1, 3, 3)
    np.testing.assert_allclose(quat_to_rotation(q2)[:, 0], R, atol=1e-15)
    assert rotation_to_quat(R[0]).shape == (4,)
    with pytest.raises(ValueError):
        quat_to_rotation(np.zeros(4))
    with pytest.raises(ValueError):
        rotation_to_quat(np.eye(4))


# ----------------------------------------------------------------------------- interpolation

def test_interpolate_poses_matches_scipy_slerp():
    rng = np.random.default_rng(RNG_SEED)
    n = 12
    t_src = np.cumsum(rng.uniform(0.05, 1.0, size=n)) + 100.0
    rots = Rotation.from_rotvec(rng.uniform(0.0, 3.1, size=(n, 3)) / np.sqrt(3))
    T_src = np.tile(np.eye(4), (n, 1, 1))
    T_src[:, :3, :3] = rots.as_matrix()
    T_src[:, :3, 3] = rng.normal(size=(n, 3))
    t_q = np.concatenate([rng.uniform(t_src[0], t_src[-1], size=200), t_src, [t_src[0], t_src[-1]]])
    T_q = interpolate_poses(t_src, T_src, t_q)
    assert T_q.shape == (t_q.size, 4, 4)
    R_ref = Slerp(t_src, rots)(t_q).as_matrix()
    np.testing.assert_allclose(T_q[:, :3, :3], R_ref, atol=1e-12)
    for k in range(3):
        np.testing.assert_allclose(T_q[:, k, 3], np.interp(t_q, t_src, T_src[:, k, 3]), atol=1e-12)
    np.testing.assert_array_equal(T_q[:, 3], np.tile([0, 0, 0, 1.0], (t_q.size, 1)))
    # tiny rotation differences (small-angle branch)
    T2 = np.stack([np.eye(4), se3_exp(np.array([1.0, 0, 0, 1e-10, 0, 0]))])
    mid = interpolate_poses(np.array([0.0, 1.0]), T2, np.array([0.5]))[0]
    np.testing.assert_allclose(so3_log(mid[:3, :3]), [5e-11, 0, 0], rtol=1e-6)
    # scalar query
    assert interpolate_poses(t_src, T_src, t_src[3]).shape == (4, 4)


def test_interpolate_poses_errors():
    t = np.array([0.0, 1.0, 2.0])
    T = np.tile(np.eye(4), (3, 1, 1))
    for bad in [-1e-9, 2.0 + 1e-9, np.nan]:
        with pytest.raises(ValueError):
            interpolate_poses(t, T, np.array([0.5, bad]))
    with pytest.raises(ValueError):
        interpolate_poses(np.array([0.0, 1.0, 1.0]), T, np.array([0.5]))
    with pytest.raises(ValueError):
        interpolate_poses(t, T[:2], np.array([0.5]))


# ----------------------------------------------------------------------------- Umeyama

def test_umeyama_against_evo():
    from evo.core.geometry import umeyama_alignment as evo_umeyama

    rng = np.random.default_rng(RNG_SEED)
    for with_scale in (False, True):
        for _ in range(5):
            src = rng.normal(size=(50, 3))
            dst = rng.normal(size=(50, 3)) + 0.5 * src
            s, R, t = umeyama_alignment(src, dst, with_scale)
            R_e, t_e, c_e = evo_umeyama(src.T, dst.T, with_scale)
            np.testing.assert_allclose(R, R_e, atol=1e-10)
            np.testing.assert_allclose(t, t_e, atol=1e-10)
            assert s == pytest.approx(c_e, abs=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_recovers_known_sim3_and_handles_reflection():
    rng = np.random.default_rng(RNG_SEED)
    src = rng.normal(scale=5.0, size=(40, 3))
    s0 = 2.7
    R0 = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    t0 = rng.normal(scale=10.0, size=3)
    dst = s0 * src @ R0.T + t0
    s, R, t = umeyama_alignment(src, dst, with_scale=True)
    assert s == pytest.approx(s0, rel=1e-12)
    np.testing.assert_allclose(R, R0, atol=1e-12)
    np.testing.assert_allclose(t, t0, atol=1e-11)
    s, R, t = umeyama_alignment(src, src @ R0.T + t0, with_scale=False)
    assert s == 1.0
    np.testing.assert_allclose(R, R0, atol=1e-12)
    # minimal planar case (3 points): still exact
    s, R, t = umeyama_alignment(src[:3], dst[:3], with_scale=True)
    np.testing.assert_allclose(s * src[:3] @ R.T + t, dst[:3], atol=1e-10)
    # a mirrored target must still give a proper rotation
    mirrored = src * np.array([1.0, 1.0, -1.0])
    _, R, _ = umeyama_alignment(src, mirrored, with_scale=True)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_umeyama_degenerate_inputs():
    rng = np.random.default_rng(RNG_SEED)
    src = rng.normal(size=(10, 3))
    with pytest.raises(ValueError):
        umeyama_alignment(src[:2], src[:2], True)
    with pytest.raises(ValueError):
        umeyama_alignment(np.ones((10, 3)), src, True)
    line = np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError):
        umeyama_alignment(line, line + 1.0, True)
    with pytest.raises(ValueError):
        umeyama_alignment(src, src[:9], True)
    bad = src.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError):
        umeyama_alignment(bad, src, False)


# ----------------------------------------------------------------------------- numba

@numba.njit(cache=True)
def _njit_caller(w, xi, T):
    R = so3_exp(w)
    w2 = so3_log(R)
    Jr = so3_right_jacobian(w) @ so3_right_jacobian_inv(w)
    Jl = so3_left_jacobian(w) @ so3_left_jacobian_inv(w)
    H = hat(w)
    v = vee(H)
    T2 = se3_compose(se3_exp(xi), se3_inverse(T))
    xi2 = se3_log(se3_exp(xi))
    A = se3_adjoint(T)
    D = decoupled_increment(T, xi)
    s = sim3_log(sim3_exp(np.append(xi, 0.2)))
    return R, w2, Jr, Jl, v, T2, xi2, A, D, s


def test_kernels_callable_from_njit():
    rng = np.random.default_rng(RNG_SEED)
    w = rng.normal(size=3)
    xi = rng.normal(size=6)
    T = _random_pose(rng)
    R, w2, Jr, Jl, v, T2, xi2, A, D, s = _njit_caller(w, xi, T)
    np.testing.assert_allclose(R, so3_exp(w), atol=0)
    np.testing.assert_allclose(so3_exp(w2), R, atol=1e-14)
    np.testing.assert_allclose(Jr, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(Jl, np.eye(3), atol=1e-12)
    np.testing.assert_array_equal(v, w)
    np.testing.assert_allclose(T2, se3_exp(xi) @ np.linalg.inv(T), atol=1e-12)
    np.testing.assert_allclose(se3_exp(xi2), se3_exp(xi), atol=1e-12)
    np.testing.assert_allclose(A, se3_adjoint(T), atol=0)
    np.testing.assert_allclose(D, decoupled_increment(T, xi), atol=0)
    np.testing.assert_allclose(sim3_exp(s), sim3_exp(np.append(xi, 0.2)), atol=1e-12)


def test_kabsch_rotation_matches_scipy_and_ignores_unused_pairs():
    """Against scipy's ``Rotation.align_vectors`` (an independent implementation) on noisy
    unit vectors; pairs outside ``use`` (here gross outliers) do not count."""
    from granite.geometry import kabsch_rotation

    rng = np.random.default_rng(4)
    R_true = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    b_p = rng.normal(size=(200, 3))
    b_p /= np.linalg.norm(b_p, axis=1, keepdims=True)
    b_t = b_p @ R_true.T + 0.01 * rng.normal(size=(200, 3))
    use = np.ones(200, dtype=bool)
    use[:20] = False
    b_t[:20] = rng.normal(size=(20, 3))  # outliers, excluded by `use`
    R = kabsch_rotation(b_p, b_t, use)
    expected, _ = Rotation.align_vectors(b_t[use], b_p[use])
    np.testing.assert_allclose(R, expected.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0
