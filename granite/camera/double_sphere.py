"""Double Sphere camera (Usenko, Demmel, Cremers 2018; Basalt ``ds``).

Parameters ``[fx, fy, cx, cy, xi, alpha]``. With ``d1 = |p|``, ``k = xi d1 + z``,
``d2 = sqrt(x^2 + y^2 + k^2)``, ``N = alpha d2 + (1 - alpha) k``:
``u = fx x / N + cx``, ``v = fy y / N + cy``.

Validity as in Basalt: projection needs ``z > -w2 d1`` with
``w1 = alpha > 0.5 ? (1 - alpha) / alpha : alpha / (1 - alpha)`` and
``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)``; unprojection needs
``r^2 < 1 / (2 alpha - 1)`` when ``alpha > 0.5``. We also reject unprojections whose
square root argument is negative or whose bearing would not project back validly.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from granite.camera import batch
from granite.camera.base import CameraModel
from granite.camera.batch import register_model
from granite.errors import ConfigError


@numba.njit(cache=True)
def _ds_project_one(kp: np.ndarray, points: np.ndarray, i: int, uv, jp, jk, want_jac: bool) -> bool:
    fx, fy, cx, cy = kp[0], kp[1], kp[2], kp[3]
    xi, alpha, w2 = kp[4], kp[5], kp[6]
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    r2 = x * x + y * y
    d1 = math.sqrt(r2 + z * z)
    if not z > -w2 * d1:
        return False
    k = xi * d1 + z
    d2 = math.sqrt(r2 + k * k)
    nrm = alpha * d2 + (1.0 - alpha) * k
    if not nrm > 0.0:
        return False
    inv = 1.0 / nrm
    mx = x * inv
    my = y * inv
    uv[i, 0] = fx * mx + cx
    uv[i, 1] = fy * my + cy
    if want_jac:
        id1 = 1.0 / d1
        id2 = 1.0 / d2
        # dk/dp = xi p / d1 + e_z ; dd2/dp = ((x, y, 0) + k dk/dp) / d2 ; dN = a dd2 + (1-a) dk
        dkx = xi * x * id1
        dky = xi * y * id1
        dkz = xi * z * id1 + 1.0
        dnx = alpha * (x + k * dkx) * id2 + (1.0 - alpha) * dkx
        dny = alpha * (y + k * dky) * id2 + (1.0 - alpha) * dky
        dnz = alpha * (k * dkz) * id2 + (1.0 - alpha) * dkz
        ax = fx * mx * inv  # fx x / N^2
        ay = fy * my * inv
        jp[i, 0, 0] = fx * inv - ax * dnx
        jp[i, 0, 1] = -ax * dny
        jp[i, 0, 2] = -ax * dnz
        jp[i, 1, 0] = -ay * dnx
        jp[i, 1, 1] = fy * inv - ay * dny
        jp[i, 1, 2] = -ay * dnz
        dn_dxi = alpha * k * d1 * id2 + (1.0 - alpha) * d1
        dn_dalpha = d2 - k
        jk[i, 0, 0] = mx
        jk[i, 0, 2] = 1.0
        jk[i, 0, 4] = -ax * dn_dxi
        jk[i, 0, 5] = -ax * dn_dalpha
        jk[i, 1, 1] = my
        jk[i, 1, 3] = 1.0
        jk[i, 1, 4] = -ay * dn_dxi
        jk[i, 1, 5] = -ay * dn_dalpha
    return True


@numba.njit(cache=True)
def _ds_unproject_one(kp: np.ndarray, uv: np.ndarray, i: int, b, jb, want_jac: bool) -> bool:
    fx, fy, cx, cy = kp[0], kp[1], kp[2], kp[3]
    xi, alpha, w2 = kp[4], kp[5], kp[6]
    mx = (uv[i, 0] - cx) / fx
    my = (uv[i, 1] - cy) / fy
    r2 = mx * mx + my * my
    arg2 = 1.0 - (2.0 * alpha - 1.0) * r2
    if not arg2 > 0.0:  # Basalt's condition r2 < 1 / (2 alpha - 1); also rejects NaN
        return False
    sqrt2 = math.sqrt(arg2)
    norm2 = alpha * sqrt2 + 1.0 - alpha
    mz = (1.0 - alpha * alpha * r2) / norm2
    arg1 = mz * mz + (1.0 - xi * xi) * r2
    if not arg1 > 0.0:
        return False
    sqrt1 = math.sqrt(arg1)
    norm1 = mz * mz + r2
    k = (mz * xi + sqrt1) / norm1
    px = k * mx
    py = k * my
    pz = k * mz - xi
    pn = math.sqrt(px * px + py * py + pz * pz)
    if not (math.isfinite(pn) and pn > 0.0 and pz > -w2 * pn):
        return False
    ipn = 1.0 / pn
    bx = px * ipn
    by = py * ipn
    bz = pz * ipn
    b[i, 0] = bx
    b[i, 1] = by
    b[i, 2] = bz
    if want_jac:
        dsqrt2 = -(2.0 * alpha - 1.0) / (2.0 * sqrt2)
        dnorm2 = alpha * dsqrt2
        dmz = (-alpha * alpha * norm2 - (1.0 - alpha * alpha * r2) * dnorm2) / (norm2 * norm2)
        dk_dr2 = ((1.0 - xi * xi) / (2.0 * sqrt1) - k) / norm1
        dk_dmz = (xi + mz / sqrt1 - 2.0 * mz * k) / norm1
        dk = dk_dr2 + dk_dmz * dmz  # total dk / dr2
        dpz = dk * mz + k * dmz  # d pz / d r2
        for col in range(2):
            m = mx if col == 0 else my
            f = fx if col == 0 else fy
            # dp / dm (dr2/dm = 2 m)
            dpx = 2.0 * m * mx * dk + (k if col == 0 else 0.0)
            dpy = 2.0 * m * my * dk + (k if col == 1 else 0.0)
            dpzc = 2.0 * m * dpz
            dot = bx * dpx + by * dpy + bz * dpzc
            s = ipn / f
            jb[i, 0, col] = (dpx - bx * dot) * s
            jb[i, 1, col] = (dpy - by * dot) * s
            jb[i, 2, col] = (dpzc - bz * dot) * s
    return True


register_model(batch.DS, _ds_project_one, _ds_unproject_one, 6,
               check_jacobians=(True, True))


class DoubleSphereCamera(CameraModel):
    """Double Sphere ``ds`` camera, parameters ``[fx, fy, cx, cy, xi, alpha]``,
    ``0 <= alpha <= 1``."""

    name = "ds"
    param_names = ("fx", "fy", "cx", "cy", "xi", "alpha")
    kernel_model = batch.DS

    def _kernel_params(self, p: np.ndarray) -> np.ndarray:
        xi, alpha = float(p[4]), float(p[5])
        if not 0.0 <= alpha <= 1.0:
            raise ConfigError(f"camera 'ds': alpha must lie in [0, 1], got {alpha}")
        w1 = (1.0 - alpha) / alpha if alpha > 0.5 else alpha / (1.0 - alpha)
        arg = 2.0 * w1 * xi + xi * xi + 1.0
        if not arg > 0.0:
            raise ConfigError(f"camera 'ds': xi={xi} and alpha={alpha} give no valid projection region")
        self.w2 = (w1 + xi) / math.sqrt(arg)
        return np.concatenate([p, [self.w2]])
