"""Predicted positions of tracked points under a known camera motion (for motion-guided tracking).

The VO knows the relative pose ``T_new_old`` (constant-velocity prediction) and, for some
points, their depth. A point with planar depth ``z`` (camera z, metres) in the old frame is
back-projected, moved and projected; a point without depth is mapped by the infinite homography
(its bearing is rotated by ``R_new_old``, the translation ignored), exact for distant points and
for pure rotation. Any :mod:`granite.camera` model works (``unproject`` / ``project``).
Feed the result to ``FrameToFrameOpticalFlow.process(t, image, predicted=(ids[valid],
uv[valid]))``.
"""

from __future__ import annotations

import numpy as np


def predict_positions(
    positions: np.ndarray,
    camera,
    T_new_old: np.ndarray,
    depths: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Where the points seen at ``positions`` (N, 2) in the old image appear in the new one.

    Args:
        positions: (N, 2) level-0 pixels in the old image.
        camera: a :mod:`granite.camera` model.
        T_new_old: (4, 4) pose of the old camera in the new camera's frame
            (``inv(T_w_new) @ T_w_old``).
        depths: optional (N,) planar depths (camera z) in the old frame; NaN, 0, negative or
            inf = unknown (rotation only: the infinite homography).
    Returns:
        (uv (N, 2), valid (N,)): valid is False where unprojection or projection fails (the
        camera model decides about points behind it; then uv is NaN).
    """
    uv_old = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    T = np.asarray(T_new_old, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"T_new_old must be 4x4, got {T.shape}")
    n = len(uv_old)
    uv = np.full((n, 2), np.nan)
    valid = np.zeros(n, dtype=bool)
    if n == 0:
        return uv, valid
    bearings, ok = camera.unproject(uv_old)
    R = T[:3, :3]
    pts = bearings @ R.T  # rotation only: directions
    if depths is not None:
        z = np.asarray(depths, dtype=np.float64).reshape(-1)
        if z.shape != (n,):
            raise ValueError(f"depths must have shape ({n},), got {z.shape}")
        with np.errstate(invalid="ignore", divide="ignore"):
            has_z = ok & np.isfinite(z) & (z > 0) & (bearings[:, 2] > 1e-9)
        if has_z.any():
            p_old = bearings[has_z] * (z[has_z] / bearings[has_z, 2])[:, None]
            pts[has_z] = p_old @ R.T + T[:3, 3]
    ok &= np.isfinite(pts).all(axis=1) & (np.abs(pts).sum(axis=1) > 1e-12)
    if ok.any():
        proj, ok_p = camera.project(pts[ok])
        idx = np.flatnonzero(ok)
        good = ok_p & np.isfinite(proj).all(axis=1)
        uv[idx[good]] = proj[good]
        valid[idx[good]] = True
    return uv, valid


def predict_positions_rotation(
    positions: np.ndarray, camera, R_new_old: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-only prediction (infinite homography ``K R K^-1`` for a pinhole camera) of
    (N, 2) pixels; ``R_new_old`` (3, 3) rotates old-camera directions into the new camera.
    Returns (uv (N, 2), valid (N,)) as :func:`predict_positions`."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R_new_old, dtype=np.float64)
    return predict_positions(positions, camera, T)
