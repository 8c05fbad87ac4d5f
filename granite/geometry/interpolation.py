"""Pose interpolation: linear in translation, spherical-linear (slerp) in rotation."""

from __future__ import annotations

import numpy as np

from granite.geometry.quaternion import quat_to_rotation, rotation_to_quat


def interpolate_poses(t_src: np.ndarray, T_src: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Interpolate 4x4 poses ``T_src`` (N,4,4) stamped ``t_src`` (N,) (seconds, strictly
    increasing) at ``t_query`` (any shape); returns poses of shape ``t_query.shape + (4, 4)``.

    Poses keep their meaning (e.g. ``T_w_c``): the translation is interpolated linearly, the
    rotation by slerp between the two bracketing samples. Raises ``ValueError`` for bad
    shapes, non-increasing ``t_src`` or a query outside ``[t_src[0], t_src[-1]]`` (no
    extrapolation); callers turn it into an ``InputError``.
    """
    t_src = np.asarray(t_src, dtype=np.float64)
    T_src = np.asarray(T_src, dtype=np.float64)
    t_query = np.asarray(t_query, dtype=np.float64)
    if t_src.ndim != 1 or t_src.size == 0:
        raise ValueError("t_src must be a non-empty 1-D array")
    if T_src.shape != (t_src.size, 4, 4):
        raise ValueError(f"T_src must have shape ({t_src.size}, 4, 4), got {T_src.shape}")
    if not np.all(np.isfinite(t_src)):
        raise ValueError("t_src contains non-finite timestamps")
    if t_src.size > 1 and not np.all(np.diff(t_src) > 0.0):
        i = int(np.argmin(np.diff(t_src) > 0.0))
        raise ValueError(
            f"t_src must be strictly increasing (t[{i}]={t_src[i]!r}, t[{i + 1}]={t_src[i + 1]!r})"
        )
    flat = t_query.reshape(-1)
    outside = ~((flat >= t_src[0]) & (flat <= t_src[-1]))  # also catches NaN
    if np.any(outside):
        bad = flat[np.argmax(outside)]
        raise ValueError(
            f"query time {bad!r} outside the interpolation range [{t_src[0]!r}, {t_src[-1]!r}]"
        )
    out = np.zeros((flat.size, 4, 4))
    out[:, 3, 3] = 1.0
    if t_src.size == 1:
        out[:] = T_src[0]
        return out.reshape(t_query.shape + (4, 4))

    i0 = np.clip(np.searchsorted(t_src, flat, side="right") - 1, 0, t_src.size - 2)
    i1 = i0 + 1
    a = (flat - t_src[i0]) / (t_src[i1] - t_src[i0])

    quats = rotation_to_quat(T_src[:, :3, :3])
    q0 = quats[i0]
    q1 = quats[i1]
    sign = np.where(np.sum(q0 * q1, axis=-1) < 0.0, -1.0, 1.0)
    q1 = q1 * sign[:, None]
    # angle between the unit quaternions, accurate for small and large angles
    omega = 2.0 * np.arctan2(np.linalg.norm(q1 - q0, axis=-1), np.linalg.norm(q1 + q0, axis=-1))
    small = omega < 1e-8
    sin_omega = np.where(small, 1.0, np.sin(omega))
    w0 = np.where(small, 1.0 - a, np.sin((1.0 - a) * omega) / sin_omega)
    w1 = np.where(small, a, np.sin(a * omega) / sin_omega)
    q = w0[:, None] * q0 + w1[:, None] * q1

    out[:, :3, :3] = quat_to_rotation(q)
    out[:, :3, 3] = (1.0 - a)[:, None] * T_src[i0, :3, 3] + a[:, None] * T_src[i1, :3, 3]
    return out.reshape(t_query.shape + (4, 4))
