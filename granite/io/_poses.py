"""Conversion between 4x4 poses and (position, Hamilton quaternion xyzw) rows, using
:mod:`granite.geometry` (imported lazily so that the io package imports on its own)."""

from __future__ import annotations

import numpy as np


def poses_from_pq(positions: np.ndarray, quats_xyzw: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` poses from ``(N, 3)`` positions and ``(N, 4)`` unit quaternions xyzw."""
    from granite.geometry import quat_to_rotation

    n = positions.shape[0]
    poses = np.zeros((n, 4, 4))
    poses[:, 3, 3] = 1.0
    poses[:, :3, 3] = positions
    if n:
        poses[:, :3, :3] = quat_to_rotation(np.asarray(quats_xyzw, dtype=np.float64))
    return poses


def pq_from_poses(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(N, 3)`` positions and ``(N, 4)`` quaternions xyzw with ``qw >= 0``."""
    from granite.geometry import rotation_to_quat

    quats = rotation_to_quat(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    quats[quats[:, 3] < 0] *= -1.0
    return np.array(poses[:, :3, 3]), quats


def pose_from_pq(position: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """One 4x4 pose from a position and a unit quaternion xyzw."""
    return poses_from_pq(np.asarray(position, float)[None], np.asarray(quat_xyzw, float)[None])[0]


def orthonormalise(R: np.ndarray, tol: float = 1e-3) -> np.ndarray | None:
    """Nearest rotation to ``R`` (SVD), or ``None`` when ``R`` is farther than ``tol`` from
    orthonormal or has a negative determinant. For poses printed with few digits."""
    R = np.asarray(R, dtype=np.float64)
    if np.max(np.abs(R.T @ R - np.eye(3))) > tol or np.linalg.det(R) <= 0:
        return None
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt
