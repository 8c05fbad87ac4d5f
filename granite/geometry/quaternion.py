"""Vectorised conversions between Hamilton unit quaternions ``(qx, qy, qz, qw)`` and rotation
matrices (TUM order; EuRoC's ``qw qx qy qz`` must be reordered by the caller)."""

from __future__ import annotations

import numpy as np


def quat_to_rotation(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of quaternions (..., 4) in ``xyzw`` order.

    The quaternions are normalised first; ``q`` and ``-q`` give the same rotation.
    Raises ``ValueError`` for a wrong shape, a non-finite or a zero-norm quaternion.
    """
    q = np.asarray(q, dtype=np.float64)
    if q.ndim < 1 or q.shape[-1] != 4:
        raise ValueError(f"quaternions must have shape (..., 4), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("quaternions contain non-finite values")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("quaternion with zero norm")
    q = q / n
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[..., 0, 1] = 2.0 * (x * y - z * w)
    R[..., 0, 2] = 2.0 * (x * z + y * w)
    R[..., 1, 0] = 2.0 * (x * y + z * w)
    R[..., 1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[..., 1, 2] = 2.0 * (y * z - x * w)
    R[..., 2, 0] = 2.0 * (x * z - y * w)
    R[..., 2, 1] = 2.0 * (y * z + x * w)
    R[..., 2, 2] = 1.0 - 2.0 * (x * x + y * y)
    return R


def rotation_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) in ``xyzw`` order with ``qw >= 0`` of rotation matrices
    (..., 3, 3) (Shepperd's method, accurate for all angles).

    Raises ``ValueError`` for a wrong shape or non-finite input.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("rotation matrices contain non-finite values")
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z; pick the largest to divide by
    cand = np.stack(
        [1.0 + r00 + r11 + r22, 1.0 + r00 - r11 - r22, 1.0 - r00 + r11 - r22, 1.0 - r00 - r11 + r22],
        axis=-1,
    )
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], axis=-1)[..., 0], 1e-300))
    a21 = R[..., 2, 1] - R[..., 1, 2]
    a02 = R[..., 0, 2] - R[..., 2, 0]
    a10 = R[..., 1, 0] - R[..., 0, 1]
    s01 = R[..., 0, 1] + R[..., 1, 0]
    s02 = R[..., 0, 2] + R[..., 2, 0]
    s12 = R[..., 1, 2] + R[..., 2, 1]
    q = np.empty(R.shape[:-2] + (4,))
    quarter = 0.25 * s
    # columns: x, y, z, w
    q[..., 0] = np.select([k == 0, k == 1, k == 2], [a21 / s, quarter, s01 / s], s02 / s)
    q[..., 1] = np.select([k == 0, k == 1, k == 2], [a02 / s, s01 / s, quarter], s12 / s)
    q[..., 2] = np.select([k == 0, k == 1, k == 2], [a10 / s, s02 / s, s12 / s], quarter)
    q[..., 3] = np.select([k == 0, k == 1, k == 2], [quarter, a21 / s, a02 / s], a10 / s)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[..., 3:4] < 0.0, -1.0, 1.0)
    return q
