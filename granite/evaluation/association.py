"""Time association of an estimate with the ground truth.

The ground truth is linearly interpolated (translation linear, rotation slerp;
:func:`granite.geometry.interpolate_poses`) at those estimate timestamps that fall inside the
ground truth's time span. Timestamps within :data:`TIME_EPS` outside the span are clamped onto
it, so that rounding in text files does not drop the first or last pose.
"""

from __future__ import annotations

import numpy as np

from granite.errors import InputError
from granite.geometry import interpolate_poses
from granite.trajectory import Trajectory

#: Seconds by which a query may lie outside a time span and still be clamped onto it.
TIME_EPS = 1e-6


def clamp_to_span(t: np.ndarray, t_first: float, t_last: float) -> tuple[np.ndarray, np.ndarray]:
    """``(inside, clamped)``: mask of ``t`` within ``[t_first, t_last]`` (+- :data:`TIME_EPS`)
    and ``t`` clipped onto the span."""
    t = np.asarray(t, dtype=np.float64)
    inside = (t >= t_first - TIME_EPS) & (t <= t_last + TIME_EPS)
    return inside, np.clip(t, t_first, t_last)


def check_nonempty(est: Trajectory, gt: Trajectory) -> None:
    """InputError for an empty estimate or ground truth."""
    if len(est) == 0:
        raise InputError("the estimate is empty")
    if len(gt) == 0:
        raise InputError("the ground truth is empty")


def associate(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """``(indices, gt_poses)``: indices of the estimate poses inside the ground truth's time
    span and the ground truth ``T_w_c`` interpolated at their timestamps ``(M, 4, 4)``.

    Raises InputError when the two trajectories do not overlap in time.
    """
    check_nonempty(est, gt)
    inside, clamped = clamp_to_span(est.timestamps, gt.timestamps[0], gt.timestamps[-1])
    indices = np.flatnonzero(inside)
    if indices.size == 0:
        raise InputError(
            f"estimate ({est.timestamps[0]:.6f} .. {est.timestamps[-1]:.6f} s) does not overlap "
            f"the ground truth ({gt.timestamps[0]:.6f} .. {gt.timestamps[-1]:.6f} s) in time"
        )
    return indices, interpolate_poses(gt.timestamps, gt.poses, clamped[indices])
