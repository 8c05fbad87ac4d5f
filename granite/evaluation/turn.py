"""Rotation error over a turn in place (issue 12: "a 360° yaw turn in place, rotation error below
1° over the whole turn").

The *turn* is the longest run of consecutive steps between ground-truth poses (interpolated at
the estimate's timestamps) that each rotate by more than ``min_rate_deg`` and move the camera
centre by at most ``max_step`` (ground-truth units): turning without moving. The error of
frame i of the turn is the angle of ``(R_est_0^T R_est_i) (R_gt_0^T R_gt_i)^T``: the estimated
rotation since the turn's first frame against the true one. It needs no alignment (relative
rotations do not depend on the world frame or the scale), so it holds across sub-maps only when
the turn lies in one sub-map: the turn is searched within the estimate's sub-maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from granite.evaluation.association import associate
from granite.geometry import so3_log
from granite.trajectory import Trajectory


@dataclass(frozen=True)
class TurnError:
    """``first``/``last``: estimate indices of the turn (inclusive); ``turned_deg``: the true
    rotation from its first to its last frame along the way (sum of the per-frame angles);
    ``errors_deg``: per frame of the turn; ``max_deg``: their maximum."""

    first: int
    last: int
    turned_deg: float
    errors_deg: np.ndarray
    max_deg: float


def _angle_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(np.linalg.norm(np.stack([so3_log(r) for r in R]), axis=1))


def turn_rotation_error(est: Trajectory, gt: Trajectory, min_rate_deg: float = 0.05,
                        max_step: float = 0.005) -> TurnError | None:
    """The rotation error over the longest turn in place (see the module docstring); None when
    the ground truth has no such run of at least 2 steps."""
    indices, gt_poses = associate(est, gt)
    submaps = est.submap_ids()[indices]
    R_gt, t_gt = gt_poses[:, :3, :3], gt_poses[:, :3, 3]
    if len(indices) < 3:
        return None
    step_deg = _angle_deg(np.einsum("nji,njk->nik", R_gt[:-1], R_gt[1:]))
    step_move = np.linalg.norm(np.diff(t_gt, axis=0), axis=1)
    # step k goes from frame k to k + 1
    turning = (step_deg > min_rate_deg) & (step_move <= max_step) & (submaps[1:] == submaps[:-1])
    best, run_start = None, None
    for k, on in enumerate(np.append(turning, False)):
        if on and run_start is None:
            run_start = k
        elif not on and run_start is not None:
            if best is None or k - run_start > best[1] - best[0]:
                best = (run_start, k)  # frames run_start .. k
            run_start = None
    if best is None or best[1] - best[0] < 2:
        return None
    a, b = best
    R_est = est.poses[indices[a:b + 1], :3, :3]
    rel_est = np.einsum("ji,njk->nik", R_est[0], R_est)
    rel_gt = np.einsum("ji,njk->nik", R_gt[a], R_gt[a:b + 1])
    errors = _angle_deg(np.einsum("nij,nkj->nik", rel_est, rel_gt))
    return TurnError(int(indices[a]), int(indices[b]), float(step_deg[a:b].sum()), errors,
                     float(errors.max()))
