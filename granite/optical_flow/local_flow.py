"""Guesses of the local-flow retry (numba): for each point the frontend could not track, the
per-axis median displacement of its nearest tracked neighbours (level-0 pixels)."""

from __future__ import annotations

import numpy as np
from numba import njit

from granite.optical_flow.patch import FASTMATH as _FASTMATH

#: A local-flow guess shorter than this (level-0 pixels) is not tried: the zero-motion pass
#: already started within its convergence basin.
_LOCAL_MIN_FLOW = 1.0
#: Nor one within this distance (level-0 pixels, squared) of where the point's earlier
#: forward attempt ended: a retry from there converges to the same place.
_LOCAL_SAME_END_SQ = 2.0**2


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def local_guesses(points, out, status, k_nearest, guess) -> bool:
    """Fill ``guess`` (N, 2) for the points not tracked (``status`` False) with the per-axis
    median displacement ``out - points`` of their ``k_nearest`` nearest tracked points (ties
    in distance: lower index first). NaN: a tracked point, a guess shorter than
    :data:`_LOCAL_MIN_FLOW`, or one ending within ``sqrt(_LOCAL_SAME_END_SQ)`` of the point's
    own ``out``. Returns False when there is nothing to try (fewer than 3 tracked points, or
    none untracked)."""
    n = points.shape[0]
    tracked = np.flatnonzero(status)
    m = tracked.shape[0]
    guess[:, :] = np.nan
    if m < 3 or m == n or k_nearest < 1:
        return False
    k_use = min(k_nearest, m)
    best_d = np.empty(k_use)
    best_i = np.empty(k_use, dtype=np.int64)
    dx = np.empty(k_use)
    dy = np.empty(k_use)
    for k in range(n):
        if status[k]:
            continue
        count = 0
        for j in range(m):
            t = tracked[j]
            d = (points[t, 0] - points[k, 0]) ** 2 + (points[t, 1] - points[k, 1]) ** 2
            if count < k_use:
                pos = count
                count += 1
            elif d < best_d[k_use - 1]:
                pos = k_use - 1
            else:
                continue
            # insertion into the sorted list of the nearest so far (ties: lower index first)
            while pos > 0 and best_d[pos - 1] > d:
                best_d[pos] = best_d[pos - 1]
                best_i[pos] = best_i[pos - 1]
                pos -= 1
            best_d[pos] = d
            best_i[pos] = t
        for j in range(k_use):
            t = best_i[j]
            dx[j] = out[t, 0] - points[t, 0]
            dy[j] = out[t, 1] - points[t, 1]
        gx = np.median(dx)
        gy = np.median(dy)
        # where an earlier pass ended (its forward result) near the guessed position, a retry
        # from there would converge to the same place
        ex = points[k, 0] + gx - out[k, 0]
        ey = points[k, 1] + gy - out[k, 1]
        if gx * gx + gy * gy >= _LOCAL_MIN_FLOW * _LOCAL_MIN_FLOW and ex * ex + ey * ey >= _LOCAL_SAME_END_SQ:
            guess[k, 0] = gx
            guess[k, 1] = gy
    return True
