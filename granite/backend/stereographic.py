"""Stereographic parametrisation of unit bearings (landmark directions in their host frame).

A bearing ``b`` (unit 3-vector, camera frame: x right, y down, z forward) is stored minimally as
its stereographic projection ``s`` (2,) from the pole ``(0, 0, -1)``:
``s = (b_x, b_y) / (1 + b_z)``, ``b = (2 s, 1 - |s|^2) / (1 + |s|^2)``; it is updated additively
(``s <- s + ds``). It is singular only for a bearing pointing exactly backwards (``b_z = -1``),
which no camera observes.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def bearing_from_stereo_into(x: float, y: float, b: np.ndarray, J: np.ndarray) -> None:
    """Write the unit bearing ``b`` (3,) of the stereographic vector ``(x, y)`` and its Jacobian
    ``db/ds`` (3,2) into preallocated arrays (allocation-free, for kernels)."""
    n2 = x * x + y * y
    inv = 1.0 / (1.0 + n2)
    b[0] = 2.0 * x * inv
    b[1] = 2.0 * y * inv
    b[2] = (1.0 - n2) * inv
    inv2 = inv * inv
    J[0, 0] = 2.0 * inv - 4.0 * x * x * inv2
    J[0, 1] = -4.0 * x * y * inv2
    J[1, 0] = J[0, 1]
    J[1, 1] = 2.0 * inv - 4.0 * y * y * inv2
    J[2, 0] = -4.0 * x * inv2
    J[2, 1] = -4.0 * y * inv2


@numba.njit(cache=True)
def bearing_from_stereo(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearing ``b`` (3,) of a stereographic 2-vector and its Jacobian ``db/ds`` (3,2)."""
    b = np.empty(3)
    J = np.empty((3, 2))
    bearing_from_stereo_into(s[0], s[1], b, J)
    return b, J


def stereo_from_bearing(bearing: np.ndarray) -> np.ndarray:
    """Stereographic 2-vector(s) of bearing(s) (..., 3); the input is normalised first."""
    b = np.asarray(bearing, dtype=np.float64)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    if np.any(b[..., 2] <= -1.0 + 1e-9):
        raise ValueError("bearing points backwards (b_z = -1): no stereographic parameter")
    return b[..., :2] / (1.0 + b[..., 2:3])


def stereo_from_bearing3(bearing) -> tuple[float, float]:
    """:func:`stereo_from_bearing` of one bearing (3 numbers) in plain float arithmetic, the
    same operations in the same order (the same bits, ``tests/test_backend_database.py``),
    without numpy's per-call overhead (landmark creation adds hundreds per keyframe)."""
    x, y, z = (float(v) for v in bearing)
    n = math.sqrt(x * x + y * y + z * z)
    if not n > 0.0:
        raise ValueError(f"bearing ({x}, {y}, {z}) has no direction")
    bz = z / n
    if bz <= -1.0 + 1e-9:
        raise ValueError("bearing points backwards (b_z = -1): no stereographic parameter")
    d = 1.0 + bz
    return (x / n) / d, (y / n) / d


def bearings_from_stereo(s: np.ndarray) -> np.ndarray:
    """Vectorised inverse of :func:`stereo_from_bearing`: (..., 2) -> unit bearings (..., 3)."""
    s = np.asarray(s, dtype=np.float64)
    n2 = np.sum(s * s, axis=-1, keepdims=True)
    return np.concatenate([2.0 * s, 1.0 - n2], axis=-1) / (1.0 + n2)
