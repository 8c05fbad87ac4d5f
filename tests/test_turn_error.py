"""Rotation error over a turn in place (granite.evaluation.turn) against a known injected drift."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from granite.evaluation.turn import turn_rotation_error
from granite.trajectory import Trajectory


def _poses(yaw_deg: np.ndarray, centres: np.ndarray, extra_yaw_deg=None) -> np.ndarray:
    """Downward-tilted camera (x right, y down, z forward) yawing about the world z axis."""
    tilt = Rotation.from_euler("x", -135, degrees=True)  # optical axis 45° below the horizon
    yaw = yaw_deg if extra_yaw_deg is None else yaw_deg + extra_yaw_deg
    R = (Rotation.from_euler("z", yaw, degrees=True) * tilt).as_matrix()
    T = np.tile(np.eye(4), (len(yaw_deg), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, centres
    return T


def _flight():
    """20 frames of leg (0.1 m per frame), 180 frames turning 2° per frame in place, 20 of leg."""
    n_leg, n_turn = 20, 180
    yaw = np.concatenate([np.zeros(n_leg), 2.0 * np.arange(1, n_turn + 1), np.full(n_leg, 360.0)])
    x = np.concatenate([0.1 * np.arange(n_leg), np.full(n_turn, 0.1 * (n_leg - 1)),
                        0.1 * (n_leg - 1) + 0.1 * np.arange(1, n_leg + 1)])
    centres = np.column_stack([x, np.zeros_like(x), np.full_like(x, 8.0)])
    t = 0.05 * np.arange(len(yaw))
    return t, yaw, centres, n_leg


def test_max_error_is_the_injected_drift_and_independent_of_the_world_frame():
    t, yaw, centres, n_leg = _flight()
    gt = Trajectory(t, _poses(yaw, centres))
    drift = np.zeros_like(yaw)
    drift[n_leg:] = 0.004 * np.arange(1, len(yaw) - n_leg + 1)  # 0.004° per frame from the turn on
    est_poses = _poses(yaw, centres, drift)
    # any world frame and scale of the estimate: relative rotations do not see them
    W = np.eye(4)
    W[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    W[:3, 3] = [5.0, -2.0, 1.0]
    est_poses = W @ est_poses
    est_poses[:, :3, 3] *= 0.37
    res = turn_rotation_error(Trajectory(t, est_poses), gt)
    assert (res.first, res.last) == (n_leg - 1, n_leg - 1 + 180)
    assert res.turned_deg == pytest.approx(360.0, abs=1e-6)
    # the turn's first frame already carries 0 drift relative to the one before it; its last
    # frame 180 steps of 0.004°
    assert res.max_deg == pytest.approx(180 * 0.004, abs=1e-6)
    np.testing.assert_allclose(res.errors_deg, 0.004 * np.arange(181), atol=1e-6)


def test_the_turn_is_searched_within_sub_maps_and_none_without_a_turn():
    t, yaw, centres, n_leg = _flight()
    gt = Trajectory(t, _poses(yaw, centres))
    submap = np.zeros(len(t), dtype=np.int64)
    submap[n_leg + 120:] = 1  # a restart 120 frames into the turn
    res = turn_rotation_error(Trajectory(t, _poses(yaw, centres), submap), gt)
    assert (res.first, res.last) == (n_leg - 1, n_leg + 119)  # the longer piece (frames 20-139)
    assert res.max_deg == pytest.approx(0.0, abs=1e-6)
    straight = Trajectory(t, _poses(np.zeros_like(yaw), centres))
    assert turn_rotation_error(straight, straight) is None
