"""SO(3) kernels: hat/vee, exponential and logarithm maps, left/right Jacobians, the Kabsch rotation.

Conventions: rotation vectors ``w`` (3,) are axis * angle in radians; ``hat(w) @ p == cross(w, p)``
(paper Eq. 2). Jacobians follow the usual definitions

* right: ``exp(w + d) ~= exp(w) @ exp(J_r(w) @ d)``
* left:  ``exp(w + d) ~= exp(J_l(w) @ d) @ exp(w)``  (``J_l(w) = J_r(-w) = R @ J_r(w)``)

All functions are ``numba.njit(cache=True)`` kernels on float64 numpy arrays (single elements, but
:func:`kabsch_rotation` over point sets) and
may be called from Python or from other njit functions. Pass numpy arrays (not lists).
"""

from __future__ import annotations

import math

import numba
import numpy as np

# Below this angle the trigonometric coefficients are evaluated by Taylor series.
_SMALL_ANGLE = 1e-3


@numba.njit(cache=True)
def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``[w]_x`` (3,3) of a 3-vector, so that ``hat(w) @ p = w x p``."""
    if w.shape[0] != 3:
        raise ValueError("hat: expected a vector of shape (3,)")
    W = np.zeros((3, 3))
    W[0, 1] = -w[2]
    W[0, 2] = w[1]
    W[1, 0] = w[2]
    W[1, 2] = -w[0]
    W[2, 0] = -w[1]
    W[2, 1] = w[0]
    return W


@numba.njit(cache=True)
def vee(W: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`: the 3-vector of the skew-symmetric part of a (3,3) matrix."""
    if W.shape[0] != 3 or W.shape[1] != 3:
        raise ValueError("vee: expected a matrix of shape (3,3)")
    w = np.empty(3)
    w[0] = 0.5 * (W[2, 1] - W[1, 2])
    w[1] = 0.5 * (W[0, 2] - W[2, 0])
    w[2] = 0.5 * (W[1, 0] - W[0, 1])
    return w


@numba.njit(cache=True)
def _so3_coeffs(theta2: float) -> tuple[float, float, float]:
    """(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3) for t = sqrt(theta2), series near 0."""
    if theta2 < _SMALL_ANGLE * _SMALL_ANGLE:
        a = 1.0 - theta2 / 6.0 * (1.0 - theta2 / 20.0)
        b = 0.5 - theta2 / 24.0 * (1.0 - theta2 / 30.0)
        c = 1.0 / 6.0 - theta2 / 120.0 * (1.0 - theta2 / 42.0)
        return a, b, c
    theta = math.sqrt(theta2)
    s = math.sin(theta)
    a = s / theta
    # 1 - cos t = 2 sin^2(t/2) avoids cancellation
    sh = math.sin(0.5 * theta)
    b = 2.0 * sh * sh / theta2
    c = (theta - s) / (theta2 * theta)
    return a, b, c


@numba.njit(cache=True)
def _poly_skew(w: np.ndarray, c0: float, c1: float, c2: float) -> np.ndarray:
    """c0 I + c1 [w]_x + c2 [w]_x^2  (with [w]_x^2 = w w^T - |w|^2 I)."""
    if w.shape[0] != 3:
        raise ValueError("expected a rotation vector of shape (3,)")
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    M = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            M[i, j] = c2 * w[i] * w[j]
        M[i, i] += c0 - c2 * theta2
    M[0, 1] -= c1 * w[2]
    M[0, 2] += c1 * w[1]
    M[1, 0] += c1 * w[2]
    M[1, 2] -= c1 * w[0]
    M[2, 0] -= c1 * w[1]
    M[2, 1] += c1 * w[0]
    return M


@numba.njit(cache=True)
def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix ``exp([w]_x)`` (Rodrigues), exact and smooth for tiny angles."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    a, b, _ = _so3_coeffs(theta2)
    return _poly_skew(w, 1.0, a, b)


@numba.njit(cache=True)
def _rotation_to_quat_single(R: np.ndarray) -> tuple[float, float, float, float]:
    """Shepperd's method; returns (qx, qy, qz, qw) with qw >= 0 (not re-normalised)."""
    r00 = R[0, 0]
    r11 = R[1, 1]
    r22 = R[2, 2]
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        qw = 0.25 * s
        qx = (R[2, 1] - R[1, 2]) / s
        qy = (R[0, 2] - R[2, 0]) / s
        qz = (R[1, 0] - R[0, 1]) / s
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        qw = (R[2, 1] - R[1, 2]) / s
        qx = 0.25 * s
        qy = (R[0, 1] + R[1, 0]) / s
        qz = (R[0, 2] + R[2, 0]) / s
    elif r11 >= r22:
        s = 2.0 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        qw = (R[0, 2] - R[2, 0]) / s
        qx = (R[0, 1] + R[1, 0]) / s
        qy = 0.25 * s
        qz = (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        qw = (R[1, 0] - R[0, 1]) / s
        qx = (R[0, 2] + R[2, 0]) / s
        qy = (R[1, 2] + R[2, 1]) / s
        qz = 0.25 * s
    if qw < 0.0:
        qx, qy, qz, qw = -qx, -qy, -qz, -qw
    return qx, qy, qz, qw


@numba.njit(cache=True)
def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``w`` with ``exp([w]_x) = R`` and ``|w| <= pi``.

    Goes through the quaternion (Shepperd) and ``2 atan2(|q_v|, q_w)``, so it is accurate
    near 0 and near pi alike. ``R`` should be a rotation matrix (3,3).
    """
    if R.shape[0] != 3 or R.shape[1] != 3:
        raise ValueError("so3_log: expected a matrix of shape (3,3)")
    qx, qy, qz, qw = _rotation_to_quat_single(R)
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    w = np.empty(3)
    if n < 1e-7 * qw:
        # theta / n = 2 atan(n / qw) / n, series in (n / qw)
        r2 = (n / qw) ** 2
        f = 2.0 / qw * (1.0 - r2 / 3.0)
    else:
        f = 2.0 * math.atan2(n, qw) / n
    w[0] = f * qx
    w[1] = f * qy
    w[2] = f * qz
    return w


@numba.njit(cache=True)
def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """Right Jacobian ``J_r(w) = I - (1-cos t)/t^2 [w]_x + (t - sin t)/t^3 [w]_x^2``."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    _, b, c = _so3_coeffs(theta2)
    return _poly_skew(w, 1.0, -b, c)


@numba.njit(cache=True)
def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """Left Jacobian ``J_l(w) = I + (1-cos t)/t^2 [w]_x + (t - sin t)/t^3 [w]_x^2 = J_r(-w)``.

    It is also the matrix ``V`` of the SE(3) exponential (``t = J_l(w) v``).
    """
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    _, b, c = _so3_coeffs(theta2)
    return _poly_skew(w, 1.0, b, c)


@numba.njit(cache=True)
def _jac_inv_coeff(theta2: float) -> float:
    """(1 - (t/2) cot(t/2)) / t^2, the [w]_x^2 coefficient of the inverse Jacobians."""
    if theta2 < _SMALL_ANGLE * _SMALL_ANGLE:
        return 1.0 / 12.0 + theta2 / 720.0 + theta2 * theta2 / 30240.0
    theta = math.sqrt(theta2)
    half = 0.5 * theta
    return (1.0 - half * math.cos(half) / math.sin(half)) / theta2


@numba.njit(cache=True)
def so3_right_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian ``I + 1/2 [w]_x + (1/t^2 - (1+cos t)/(2 t sin t)) [w]_x^2``
    (singular at |w| = 2 pi)."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    return _poly_skew(w, 1.0, 0.5, _jac_inv_coeff(theta2))


@numba.njit(cache=True)
def so3_left_jacobian_inv(w: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian ``I - 1/2 [w]_x + (1/t^2 - (1+cos t)/(2 t sin t)) [w]_x^2``."""
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    return _poly_skew(w, 1.0, -0.5, _jac_inv_coeff(theta2))


@numba.njit(cache=True, nogil=True)
def kabsch_rotation(b_p: np.ndarray, b_t: np.ndarray, use: np.ndarray) -> np.ndarray:
    """``R`` minimising ``sum |b_t - R b_p|^2`` over the pairs ``use`` ((n, 3) each, (n,) bool;
    a proper rotation: Kabsch / Umeyama without scale)."""
    M = np.zeros((3, 3))
    for i in range(b_p.shape[0]):
        if use[i]:
            for r in range(3):
                for c in range(3):
                    M[r, c] += b_t[i, r] * b_p[i, c]
    U, _, Vt = np.linalg.svd(M)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt
