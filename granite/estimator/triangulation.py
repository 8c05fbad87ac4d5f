"""Two-view triangulation of bearing vectors.

Convention: ``R_c_k, t_c_k`` map points from keyframe ``k`` into frame ``c``
(``p_c = R_c_k p_k + t_c_k``); bearings are unit vectors in their own camera frame.
"""

from __future__ import annotations

import numpy as np


def triangulate_bearings(
    R_c_k: np.ndarray, t_c_k: np.ndarray, bearings_k: np.ndarray, bearings_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate points seen along ``bearings_k`` (frame k) and ``bearings_c`` (frame c).

    Uses the optimal-in-depth linear solution (minimises the distance between the two rays).
    Returns ``(points_k (N,3) in frame k, valid (N,))``; a point is valid when it lies in front
    of both cameras (positive ray parameters) and the rays are not parallel.
    """
    bk = np.asarray(bearings_k, dtype=np.float64)
    bc = np.asarray(bearings_c, dtype=np.float64)
    # Frame c's centre and ray, expressed in frame k.
    R_k_c = R_c_k.T
    centre_c = -R_k_c @ t_c_k
    dc = bc @ R_k_c.T
    # Solve  lk * bk - lc * dc = centre_c  in the least-squares sense, per point.
    a = np.einsum("ij,ij->i", bk, bk)
    b = np.einsum("ij,ij->i", bk, dc)
    c = np.einsum("ij,ij->i", dc, dc)
    d = bk @ centre_c
    e = dc @ centre_c
    denom = a * c - b * b
    ok = denom > 1e-12
    safe = np.where(ok, denom, 1.0)
    lk = (c * d - b * e) / safe
    lc = (b * d - a * e) / safe
    points = 0.5 * (lk[:, None] * bk + centre_c + lc[:, None] * dc)
    valid = ok & (lk > 0) & (lc > 0) & np.all(np.isfinite(points), axis=1)
    return points, valid


def parallax_angles(points_k: np.ndarray, R_c_k: np.ndarray, t_c_k: np.ndarray) -> np.ndarray:
    """Angle (radians) between the rays from both camera centres to each point (frame k)."""
    centre_c = -R_c_k.T @ t_c_k
    ray_k = points_k
    ray_c = points_k - centre_c
    cos = np.einsum("ij,ij->i", ray_k, ray_c) / (
        np.linalg.norm(ray_k, axis=1) * np.linalg.norm(ray_c, axis=1) + 1e-300
    )
    return np.arccos(np.clip(cos, -1.0, 1.0))
