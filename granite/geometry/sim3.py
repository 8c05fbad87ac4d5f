"""Sim(3) exponential and logarithm in closed form.

A similarity is a 4x4 matrix ``S = [[s R, t], [0, 1]]`` mapping ``p -> s R p + t``. Tangent
vectors are ``[v, w, sigma]`` (7,) with scale ``s = exp(sigma)``:

``sim3_exp([v, w, sigma]) = [[exp(sigma) exp([w]_x), W v], [0, 1]]`` with
``W = integral_0^1 exp(sigma tau) exp(tau [w]_x) dtau = A I + B [w]_x + C [w]_x^2``.

The coefficients are evaluated stably for sigma -> 0 and small angles (series branches), so
the maps are smooth through the SE(3) case. Both are ``numba.njit(cache=True)`` kernels.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from granite.geometry.so3 import _poly_skew, so3_exp, so3_log

_SMALL_ANGLE = 1e-3
_SERIES_SIGMA = 2.0


@numba.njit(cache=True)
def _moments(sigma: float, nmax: int) -> np.ndarray:
    """f_n(sigma) = integral_0^1 tau^n exp(sigma tau) dtau for n = 0..nmax."""
    f = np.empty(nmax + 1)
    if abs(sigma) < _SERIES_SIGMA:
        # sum_k sigma^k / (k! (n + k + 1)); 40 terms reach machine precision for |sigma| < 2
        for n in range(nmax + 1):
            term = 1.0
            acc = 0.0
            for k in range(40):
                acc += term / (n + k + 1)
                term *= sigma / (k + 1)
            f[n] = acc
    else:
        es = math.exp(sigma)
        f[0] = math.expm1(sigma) / sigma
        for n in range(1, nmax + 1):
            f[n] = (es - n * f[n - 1]) / sigma
    return f


@numba.njit(cache=True)
def _sim3_W_coeffs(theta2: float, sigma: float) -> tuple[float, float, float]:
    """Coefficients (A, B, C) of W = A I + B [w]_x + C [w]_x^2."""
    f = _moments(sigma, 6)
    A = f[0]
    if theta2 < _SMALL_ANGLE * _SMALL_ANGLE:
        # sin(t tau)/t and (1 - cos(t tau))/t^2 expanded in t
        B = f[1] - theta2 / 6.0 * f[3] + theta2 * theta2 / 120.0 * f[5]
        C = 0.5 * f[2] - theta2 / 24.0 * f[4] + theta2 * theta2 / 720.0 * f[6]
        return A, B, C
    theta = math.sqrt(theta2)
    es = math.exp(sigma)
    sh = math.sin(0.5 * theta)
    # exp(sigma + i theta) - 1, real part without cancellation
    a_r = math.expm1(sigma) * math.cos(theta) - 2.0 * sh * sh
    a_i = es * math.sin(theta)
    den = sigma * sigma + theta2
    re_g = (sigma * a_r + theta * a_i) / den
    im_g = (sigma * a_i - theta * a_r) / den
    B = im_g / theta
    C = (A - re_g) / theta2
    return A, B, C


@numba.njit(cache=True)
def _sim3_W(w: np.ndarray, sigma: float) -> np.ndarray:
    theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    A, B, C = _sim3_W_coeffs(theta2, sigma)
    return _poly_skew(w, A, B, C)


@numba.njit(cache=True)
def sim3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 similarity ``[[exp(sigma) R, W v], [0, 1]]`` of ``xi = [v, w, sigma]`` (7,)."""
    if xi.shape[0] != 7:
        raise ValueError("sim3_exp: expected a vector of shape (7,) = [v, w, sigma]")
    w = xi[3:6].copy()
    sigma = xi[6]
    R = so3_exp(w)
    W = _sim3_W(w, sigma)
    s = math.exp(sigma)
    S = np.zeros((4, 4))
    for i in range(3):
        for j in range(3):
            S[i, j] = s * R[i, j]
        S[i, 3] = W[i, 0] * xi[0] + W[i, 1] * xi[1] + W[i, 2] * xi[2]
    S[3, 3] = 1.0
    return S


@numba.njit(cache=True)
def _solve3(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve M x = b for a 3x3 matrix (adjugate / Cramer)."""
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    c10 = M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]
    c11 = M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]
    c12 = M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]
    c20 = M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]
    c21 = M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]
    c22 = M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    x = np.empty(3)
    x[0] = (c00 * b[0] + c10 * b[1] + c20 * b[2]) / det
    x[1] = (c01 * b[0] + c11 * b[1] + c21 * b[2]) / det
    x[2] = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / det
    return x


@numba.njit(cache=True)
def sim3_log(S: np.ndarray) -> np.ndarray:
    """Tangent vector ``[v, w, sigma]`` (7,) of a 4x4 similarity ``[[s R, t], [0, 1]]``
    (``s > 0``, ``|w| <= pi``); the inverse of :func:`sim3_exp`."""
    if S.shape[0] != 4 or S.shape[1] != 4:
        raise ValueError("sim3_log: expected a 4x4 matrix")
    sR = S[:3, :3].copy()
    det = (
        sR[0, 0] * (sR[1, 1] * sR[2, 2] - sR[1, 2] * sR[2, 1])
        - sR[0, 1] * (sR[1, 0] * sR[2, 2] - sR[1, 2] * sR[2, 0])
        + sR[0, 2] * (sR[1, 0] * sR[2, 1] - sR[1, 1] * sR[2, 0])
    )
    if not det > 0.0:
        raise ValueError("sim3_log: the 3x3 block must be a positive scale times a rotation")
    s = det ** (1.0 / 3.0)
    R = sR / s
    w = so3_log(R)
    sigma = math.log(s)
    W = _sim3_W(w, sigma)
    v = _solve3(W, S[:3, 3].copy())
    xi = np.empty(7)
    xi[0:3] = v
    xi[3:6] = w
    xi[6] = sigma
    return xi
