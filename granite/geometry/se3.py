"""SE(3) kernels on 4x4 homogeneous matrices.

``T_a_b`` maps points of frame ``b`` into frame ``a`` (``p_a = R p_b + t``). Twists are
``xi = [v, w]`` (translation part first, as Basalt/Sophus), with
``se3_exp(xi) = [[exp([w]_x), J_l(w) v], [0, 1]]``.

All functions are ``numba.njit(cache=True)`` kernels on float64 numpy arrays, callable from
Python or from other njit functions.
"""

from __future__ import annotations

import numba
import numpy as np

from granite.geometry.so3 import (
    _poly_skew,
    _so3_coeffs,
    so3_exp,
    so3_left_jacobian_inv,
    so3_log,
)


@numba.njit(cache=True)
def _check_T(T: np.ndarray) -> None:
    if T.shape[0] != 4 or T.shape[1] != 4:
        raise ValueError("expected a 4x4 homogeneous matrix")


@numba.njit(cache=True)
def _check_xi(xi: np.ndarray) -> None:
    if xi.shape[0] != 6:
        raise ValueError("expected a twist of shape (6,) = [v, w]")


@numba.njit(cache=True)
def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 pose ``exp(xi^)`` of a twist ``xi = [v, w]`` (6,)."""
    _check_xi(xi)
    w = xi[3:6].copy()
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    a, b, c = _so3_coeffs(theta2)
    R = _poly_skew(w, 1.0, a, b)
    V = _poly_skew(w, 1.0, b, c)
    T = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            T[i, j] = R[i, j]
        T[i, 3] = V[i, 0] * xi[0] + V[i, 1] * xi[1] + V[i, 2] * xi[2]
    T[3, 3] = 1.0
    return T


@numba.njit(cache=True)
def se3_log(T: np.ndarray) -> np.ndarray:
    """Twist ``[v, w]`` (6,) with ``se3_exp(xi) = T`` and ``|w| <= pi``."""
    _check_T(T)
    R = T[:3, :3].copy()
    w = so3_log(R)
    Vinv = so3_left_jacobian_inv(w)
    xi = np.empty(6)
    for i in range(3):
        xi[i] = Vinv[i, 0] * T[0, 3] + Vinv[i, 1] * T[1, 3] + Vinv[i, 2] * T[2, 3]
        xi[3 + i] = w[i]
    return xi


@numba.njit(cache=True)
def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse pose: ``T_b_a`` from ``T_a_b`` (``[[R^T, -R^T t], [0, 1]]``)."""
    _check_T(T)
    Ti = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            Ti[i, j] = T[j, i]
        Ti[i, 3] = -(T[0, i] * T[0, 3] + T[1, i] * T[1, 3] + T[2, i] * T[2, 3])
    Ti[3, 3] = 1.0
    return Ti


@numba.njit(cache=True)
def se3_compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Product ``A @ B`` of two rigid 4x4 poses (e.g. ``T_a_c = T_a_b @ T_b_c``); the last row
    is set to exactly ``[0, 0, 0, 1]``."""
    _check_T(A)
    _check_T(B)
    C = np.zeros((4, 4))
    for i in range(3):
        for j in range(4):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
        C[i, 3] += A[i, 3]
    C[3, 3] = 1.0
    return C


@numba.njit(cache=True)
def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint (6,6) of paper Eq. 3 for ``[v, w]`` twists: ``[[R, [t]_x R], [0, R]]``,
    so that ``T @ se3_exp(xi) @ T^-1 = se3_exp(Adj_T @ xi)``."""
    _check_T(T)
    A = np.zeros((6, 6))
    t0 = T[0, 3]
    t1 = T[1, 3]
    t2 = T[2, 3]
    for j in range(3):
        r0 = T[0, j]
        r1 = T[1, j]
        r2 = T[2, j]
        A[0, j] = r0
        A[1, j] = r1
        A[2, j] = r2
        A[3, 3 + j] = r0
        A[4, 3 + j] = r1
        A[5, 3 + j] = r2
        # [t]_x R, column j = t x R[:, j]
        A[0, 3 + j] = t1 * r2 - t2 * r1
        A[1, 3 + j] = t2 * r0 - t0 * r2
        A[2, 3 + j] = t0 * r1 - t1 * r0
    return A


@numba.njit(cache=True)
def decoupled_increment(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Decoupled left increment of paper Eq. 14: ``R <- exp([w]_x) R``, ``t <- t + v``."""
    _check_T(T)
    _check_xi(xi)
    dR = so3_exp(xi[3:6].copy())
    out = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            out[i, j] = dR[i, 0] * T[0, j] + dR[i, 1] * T[1, j] + dR[i, 2] * T[2, j]
        out[i, 3] = T[i, 3] + xi[i]
    out[3, 3] = 1.0
    return out


__all__ = [
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "se3_compose",
    "se3_adjoint",
    "decoupled_increment",
]
