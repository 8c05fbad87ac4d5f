"""Kannala-Brandt fisheye camera, 4 distortion coefficients (Basalt ``kb4``, OpenCV fisheye).

Parameters ``[fx, fy, cx, cy, k1, k2, k3, k4]``. With ``r = sqrt(x^2 + y^2)`` and
``theta = atan2(r, z)``: ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
k4 theta^8)``, ``u = fx theta_d x / r + cx``, ``v = fy theta_d y / r + cy`` (pinhole
formula on the optical axis, ``r < sqrt(eps)``, where ``z >= sqrt(eps)`` is required).

Validity: Basalt accepts every off-axis point; we additionally require
``theta < theta_max``, the first angle where ``d theta_d / d theta`` vanishes (pi if never), so
that projection is invertible on the valid set. Unprojection solves ``theta_d(theta)`` with
safeguarded Newton iterations and is valid for ``theta_d < theta_d(theta_max)``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from granite.camera import batch
from granite.camera.base import CameraModel
from granite.camera.batch import register_model
from granite.camera.pinhole import EPS_SQRT, _pinhole_project_one

_SMALL_TD = 1e-6


@numba.njit(cache=True)
def _kb4_poly(theta: float, k1: float, k2: float, k3: float, k4: float) -> tuple[float, float]:
    """(theta_d, d theta_d / d theta)."""
    t2 = theta * theta
    td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    dtd = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    return td, dtd


@numba.njit(cache=True)
def _kb4_project_one(kp: np.ndarray, points: np.ndarray, i: int, uv, jp, jk, want_jac: bool) -> bool:
    fx, fy, cx, cy = kp[0], kp[1], kp[2], kp[3]
    k1, k2, k3, k4 = kp[4], kp[5], kp[6], kp[7]
    theta_max = kp[8]
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    r2 = x * x + y * y
    r = math.sqrt(r2)
    if r > EPS_SQRT:
        theta = math.atan2(r, z)
        if not theta < theta_max:
            return False
        td, dtd = _kb4_poly(theta, k1, k2, k3, k4)
        q = td / r
        mx = x * q
        my = y * q
        uv[i, 0] = fx * mx + cx
        uv[i, 1] = fy * my + cy
        if want_jac:
            d2 = r2 + z * z
            h = (dtd * z * r / d2 - td) / (r2 * r)  # (dq/dr) / r
            dqdz = -dtd / d2
            jp[i, 0, 0] = fx * (q + x * x * h)
            jp[i, 0, 1] = fx * x * y * h
            jp[i, 0, 2] = fx * x * dqdz
            jp[i, 1, 0] = fy * x * y * h
            jp[i, 1, 1] = fy * (q + y * y * h)
            jp[i, 1, 2] = fy * y * dqdz
            jk[i, 0, 0] = mx
            jk[i, 0, 2] = 1.0
            jk[i, 1, 1] = my
            jk[i, 1, 3] = 1.0
            t2 = theta * theta
            tp = theta * t2  # theta^3, theta^5, theta^7, theta^9
            ax = fx * x / r
            ay = fy * y / r
            for j in range(4):
                jk[i, 0, 4 + j] = ax * tp
                jk[i, 1, 4 + j] = ay * tp
                tp *= t2
        return True
    # on the optical axis the model is the pinhole (the distortion derivatives stay 0)
    return _pinhole_project_one(kp, points, i, uv, jp, jk, want_jac)


@numba.njit(cache=True)
def _kb4_solve_theta(kp: np.ndarray, td: float) -> tuple[float, float, bool]:
    """theta with theta_d(theta) = td on [0, theta_max]; returns (theta, dtheta_d/dtheta, ok)."""
    k1, k2, k3, k4 = kp[4], kp[5], kp[6], kp[7]
    theta_max = kp[8]
    lo = 0.0
    hi = theta_max
    theta = min(td, theta_max)
    for _ in range(60):
        f, df = _kb4_poly(theta, k1, k2, k3, k4)
        f -= td
        if f > 0.0:
            hi = theta
        else:
            lo = theta
        if df > 0.0:
            new = theta - f / df
        else:
            new = 0.5 * (lo + hi)
        if not (new >= lo and new <= hi):
            new = 0.5 * (lo + hi)
        step = abs(new - theta)
        theta = new
        if step <= 1e-14 * theta or step == 0.0:
            break
    f, df = _kb4_poly(theta, k1, k2, k3, k4)
    ok = abs(f - td) <= 1e-12 * (1.0 + td) and df > 0.0
    return theta, df, ok


@numba.njit(cache=True)
def _kb4_unproject_one(kp: np.ndarray, uv: np.ndarray, i: int, b, jb, want_jac: bool) -> bool:
    fx, fy, cx, cy = kp[0], kp[1], kp[2], kp[3]
    k1 = kp[4]
    td_max = kp[9]
    mx = (uv[i, 0] - cx) / fx
    my = (uv[i, 1] - cy) / fy
    td = math.sqrt(mx * mx + my * my)
    if not td < td_max:  # also rejects NaN
        return False
    theta, dtd, ok = _kb4_solve_theta(kp, td)
    if not ok:
        return False
    sin_t = math.sin(theta)
    cos_t = math.cos(theta)
    c = k1 + 1.0 / 6.0
    if td < _SMALL_TD:
        s = 1.0 - c * td * td
        g = -2.0 * c  # (dS/dtd) / td
    else:
        s = sin_t / td
        g = (cos_t * td / dtd - sin_t) / (td * td * td)
    b[i, 0] = s * mx
    b[i, 1] = s * my
    b[i, 2] = cos_t
    if want_jac:
        dth = 1.0 / dtd
        # d/dmx, d/dmy, then divide by fx, fy
        jb[i, 0, 0] = (s + mx * mx * g) / fx
        jb[i, 0, 1] = mx * my * g / fy
        jb[i, 1, 0] = mx * my * g / fx
        jb[i, 1, 1] = (s + my * my * g) / fy
        jb[i, 2, 0] = -s * dth * mx / fx
        jb[i, 2, 1] = -s * dth * my / fy
    return True


register_model(batch.KB4, _kb4_project_one, _kb4_unproject_one, 8,
               check_jacobians=(True, False))


def kb4_theta_max(k: np.ndarray) -> float:
    """Smallest theta in (0, pi] where d theta_d / d theta = 0, or pi when there is none."""
    k1, k2, k3, k4 = (float(v) for v in k)
    # 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3 + 9 k4 s^4 with s = theta^2
    coeffs = [9.0 * k4, 7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]
    roots = np.roots(coeffs) if any(c != 0.0 for c in coeffs[:-1]) else np.array([])
    cands = [
        r.real
        for r in roots
        if abs(r.imag) <= 1e-9 * max(1.0, abs(r)) and 0.0 < r.real <= math.pi**2
    ]
    if not cands:
        return math.pi
    s = min(cands)
    # refine the root by bisection on the derivative's sign (np.roots is not exact)
    lo, hi = 0.0, min(math.sqrt(s) * 1.01, math.pi)
    def d(t: float) -> float:
        return _kb4_poly(t, k1, k2, k3, k4)[1]
    if d(hi) > 0.0:
        return min(math.sqrt(s), math.pi)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if d(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return lo


class KannalaBrandtCamera(CameraModel):
    """Kannala-Brandt ``kb4`` camera, parameters ``[fx, fy, cx, cy, k1, k2, k3, k4]``."""

    name = "kb4"
    param_names = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    kernel_model = batch.KB4

    def _kernel_params(self, p: np.ndarray) -> np.ndarray:
        theta_max = kb4_theta_max(p[4:8])
        td_max = _kb4_poly(theta_max, p[4], p[5], p[6], p[7])[0]
        self.theta_max = theta_max
        return np.concatenate([p, [theta_max, td_max]])
