"""Pinhole camera ``[fx, fy, cx, cy]``: ``u = fx x / z + cx``, ``v = fy y / z + cy``.

Valid projections need ``z >= sqrt(eps)`` (as Basalt); every finite pixel unprojects.
The ``pinhole_*`` numba kernels take the parameter vector and (N,3) points / (N,2) pixels
and may be called from other njit code.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from granite.camera.base import CameraModel

EPS_SQRT = 1.4901161193847656e-08  # sqrt(float64 eps), Basalt's epsilonSqrt


@numba.njit(cache=True)
def pinhole_project(params: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = points.shape[0]
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    uv = np.zeros((n, 2))
    valid = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (z >= EPS_SQRT and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        iz = 1.0 / z
        u = fx * (x * iz) + cx
        v = fy * (y * iz) + cy
        if math.isfinite(u) and math.isfinite(v):
            uv[i, 0] = u
            uv[i, 1] = v
            valid[i] = True
    return uv, valid


@numba.njit(cache=True)
def pinhole_project_jacobians(params: np.ndarray, points: np.ndarray):
    n = points.shape[0]
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    uv = np.zeros((n, 2))
    jp = np.zeros((n, 2, 3))
    jk = np.zeros((n, 2, 4))
    valid = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        if not (z >= EPS_SQRT and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        iz = 1.0 / z
        mx = x * iz
        my = y * iz
        u = fx * mx + cx
        v = fy * my + cy
        if not (math.isfinite(u) and math.isfinite(v)):
            continue
        uv[i, 0] = u
        uv[i, 1] = v
        jp[i, 0, 0] = fx * iz
        jp[i, 0, 2] = -fx * mx * iz
        jp[i, 1, 1] = fy * iz
        jp[i, 1, 2] = -fy * my * iz
        jk[i, 0, 0] = mx
        jk[i, 0, 2] = 1.0
        jk[i, 1, 1] = my
        jk[i, 1, 3] = 1.0
        valid[i] = True
    return uv, jp, jk, valid


@numba.njit(cache=True)
def pinhole_unproject(params: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = uv.shape[0]
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    b = np.zeros((n, 3))
    valid = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        mx = (uv[i, 0] - cx) / fx
        my = (uv[i, 1] - cy) / fy
        nrm = math.sqrt(mx * mx + my * my + 1.0)
        if not math.isfinite(nrm):
            continue
        inv = 1.0 / nrm
        b[i, 0] = mx * inv
        b[i, 1] = my * inv
        b[i, 2] = inv
        valid[i] = True
    return b, valid


@numba.njit(cache=True)
def pinhole_unproject_jacobians(params: np.ndarray, uv: np.ndarray):
    n = uv.shape[0]
    fx, fy, cx, cy = params[0], params[1], params[2], params[3]
    b = np.zeros((n, 3))
    jb = np.zeros((n, 3, 2))
    valid = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        mx = (uv[i, 0] - cx) / fx
        my = (uv[i, 1] - cy) / fy
        nrm = math.sqrt(mx * mx + my * my + 1.0)
        if not math.isfinite(nrm):
            continue
        inv = 1.0 / nrm
        bx = mx * inv
        by = my * inv
        bz = inv
        b[i, 0] = bx
        b[i, 1] = by
        b[i, 2] = bz
        # d(m/|m|)/dm = (I - b b^T)/|m|, dm/du = e_x/fx, dm/dv = e_y/fy
        su = inv / fx
        sv = inv / fy
        jb[i, 0, 0] = (1.0 - bx * bx) * su
        jb[i, 1, 0] = -by * bx * su
        jb[i, 2, 0] = -bz * bx * su
        jb[i, 0, 1] = -bx * by * sv
        jb[i, 1, 1] = (1.0 - by * by) * sv
        jb[i, 2, 1] = -bz * by * sv
        valid[i] = True
    return b, jb, valid


class PinholeCamera(CameraModel):
    """Pinhole camera, parameters ``[fx, fy, cx, cy]`` (pixels)."""

    name = "pinhole"
    param_names = ("fx", "fy", "cx", "cy")
    _k_project = staticmethod(pinhole_project)
    _k_project_jac = staticmethod(pinhole_project_jacobians)
    _k_unproject = staticmethod(pinhole_unproject)
    _k_unproject_jac = staticmethod(pinhole_unproject_jacobians)
