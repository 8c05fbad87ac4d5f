"""Ground-truth optical flow from a depth map and camera poses (for tests and benchmarks).

A pixel ``(u, v)`` of frame i with planar depth ``z`` (camera z, metres; 0 or inf = no
surface) is back-projected as ``p_ci = z * b / b_z`` with ``b`` the camera's bearing of
``(u, v)``, moved to frame j by ``T_cj_ci = inv(T_w_cj) @ T_w_ci`` and projected. Depth at a
sub-pixel position is interpolated bilinearly from the four surrounding pixel centres and is
rejected at depth discontinuities (the four depths differ by more than ``max_depth_ratio``).
"""

from __future__ import annotations

import numpy as np


def depth_at(depth: np.ndarray, uv: np.ndarray, max_depth_ratio: float = 1.02) -> np.ndarray:
    """Bilinear planar depth at (N, 2) pixel positions; NaN where unknown or discontinuous."""
    h, w = depth.shape
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(uv), np.nan)
    x0 = np.floor(uv[:, 0]).astype(np.int64)
    y0 = np.floor(uv[:, 1]).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h) & np.isfinite(uv).all(axis=1)
    if not inside.any():
        return out
    xi, yi = x0[inside], y0[inside]
    d = np.stack(
        [depth[yi, xi], depth[yi, xi + 1], depth[yi + 1, xi], depth[yi + 1, xi + 1]], axis=1
    ).astype(np.float64)
    ok = np.all(np.isfinite(d) & (d > 0), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ok &= d.max(axis=1) <= max_depth_ratio * d.min(axis=1)
    d = np.where(ok[:, None], d, 0.0)  # no inf * 0 for rows that are rejected anyway
    fx = uv[inside, 0] - xi
    fy = uv[inside, 1] - yi
    value = (
        (1 - fx) * (1 - fy) * d[:, 0] + fx * (1 - fy) * d[:, 1]
        + (1 - fx) * fy * d[:, 2] + fx * fy * d[:, 3]
    )
    vals = np.full(len(xi), np.nan)
    vals[ok] = value[ok]
    out[inside] = vals
    return out


def ground_truth_flow(
    uv_i: np.ndarray,
    depth_i: np.ndarray,
    T_w_ci: np.ndarray,
    T_w_cj: np.ndarray,
    camera,
    max_depth_ratio: float = 1.02,
) -> tuple[np.ndarray, np.ndarray]:
    """Where the surface points seen at ``uv_i`` (N, 2) in frame i appear in frame j.

    Args:
        depth_i: planar depth map of frame i (H, W).
        T_w_ci, T_w_cj: camera-to-world poses (4, 4) of frames i and j.
        camera: a :mod:`granite.camera` model (``unproject`` / ``project``).
    Returns:
        (uv_j (N, 2), valid (N,)): valid is False where the depth is unknown or
        discontinuous, the projection fails, or the point is behind camera j.
    """
    uv_i = np.asarray(uv_i, dtype=np.float64).reshape(-1, 2)
    z = depth_at(depth_i, uv_i, max_depth_ratio)
    bearings, ok_b = camera.unproject(uv_i)
    valid = ok_b & np.isfinite(z) & (bearings[:, 2] > 1e-9)
    p_ci = np.zeros((len(uv_i), 3))
    p_ci[valid] = bearings[valid] * (z[valid] / bearings[valid, 2])[:, None]
    T_cj_ci = np.linalg.inv(T_w_cj) @ T_w_ci
    p_cj = p_ci @ T_cj_ci[:3, :3].T + T_cj_ci[:3, 3]
    valid &= p_cj[:, 2] > 1e-6
    uv_j = np.zeros_like(uv_i)
    if valid.any():
        proj, ok_p = camera.project(p_cj[valid])
        uv_j[valid] = proj
        idx = np.flatnonzero(valid)
        valid[idx[~ok_p]] = False
    return uv_j, valid
