"""Pinhole camera ``[fx, fy, cx, cy]``: ``u = fx x / z + cx``, ``v = fy y / z + cy``.

Valid projections need ``z >= sqrt(eps)`` (as Basalt); every finite pixel unprojects.
Per-point kernels for :mod:`granite.camera.batch`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from granite.camera import batch
from granite.camera.base import CameraModel
from granite.camera.batch import register_model

EPS_SQRT = 1.4901161193847656e-08  # sqrt(float64 eps), Basalt's epsilonSqrt


@numba.njit(cache=True)
def _pinhole_project_one(kp: np.ndarray, points: np.ndarray, i: int, uv, jp, jk,
                         want_jac: bool) -> bool:
    fx, fy, cx, cy = kp[0], kp[1], kp[2], kp[3]
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    if not (z >= EPS_SQRT and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    iz = 1.0 / z
    mx, my = x * iz, y * iz
    uv[i, 0] = fx * mx + cx
    uv[i, 1] = fy * my + cy
    if want_jac:
        jp[i, 0, 0] = fx * iz
        jp[i, 0, 2] = -fx * mx * iz
        jp[i, 1, 1] = fy * iz
        jp[i, 1, 2] = -fy * my * iz
        jk[i, 0, 0] = mx
        jk[i, 0, 2] = 1.0
        jk[i, 1, 1] = my
        jk[i, 1, 3] = 1.0
    return True


@numba.njit(cache=True)
def _pinhole_unproject_one(kp: np.ndarray, uv: np.ndarray, i: int, b, jb,
                           want_jac: bool) -> bool:
    fx, fy, cx, cy = kp[0], kp[1], kp[2], kp[3]
    mx = (uv[i, 0] - cx) / fx
    my = (uv[i, 1] - cy) / fy
    nrm = math.sqrt(mx * mx + my * my + 1.0)
    if not math.isfinite(nrm):
        return False
    inv = 1.0 / nrm
    bx = mx * inv
    by = my * inv
    bz = inv
    b[i, 0] = bx
    b[i, 1] = by
    b[i, 2] = bz
    if want_jac:
        # d(m/|m|)/dm = (I - b b^T)/|m|, dm/du = e_x/fx, dm/dv = e_y/fy
        su = inv / fx
        sv = inv / fy
        jb[i, 0, 0] = (1.0 - bx * bx) * su
        jb[i, 1, 0] = -by * bx * su
        jb[i, 2, 0] = -bz * bx * su
        jb[i, 0, 1] = -bx * by * sv
        jb[i, 1, 1] = (1.0 - by * by) * sv
        jb[i, 2, 1] = -bz * by * sv
    return True


register_model(batch.PINHOLE, _pinhole_project_one, _pinhole_unproject_one, 4,
               check_jacobians=(False, False))


class PinholeCamera(CameraModel):
    """Pinhole camera, parameters ``[fx, fy, cx, cy]`` (pixels)."""

    name = "pinhole"
    param_names = ("fx", "fy", "cx", "cy")
    kernel_model = batch.PINHOLE
