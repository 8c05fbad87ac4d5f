"""True relative scale error over time (granite.evaluation.scale_drift)."""

from __future__ import annotations

import numpy as np
import pytest

from granite.evaluation import relative_scale_error, scale_drift_rate
from granite.geometry import so3_exp
from granite.trajectory import Trajectory


def _line(speeds: np.ndarray, dt: float = 0.05) -> Trajectory:
    """Camera flying along x with per-step speed ``speeds`` (m/s), slowly yawing."""
    steps = np.concatenate([[0.0], np.cumsum(speeds[:-1] * dt)])
    n = len(speeds)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = steps
    poses[:, 1, 3] = 0.1 * np.sin(steps)
    for k in range(n):
        poses[k, :3, :3] = so3_exp(np.array([0.0, 0.0, 0.01 * k]))
    return Trajectory(np.arange(n) * dt, poses)


def _scaled(traj: Trajectory, s: float, submap=None) -> Trajectory:
    poses = traj.poses.copy()
    poses[:, :3, 3] *= s
    return Trajectory(traj.timestamps, poses, submap)


def test_a_uniformly_scaled_estimate_has_no_scale_error():
    gt = _line(np.full(200, 2.0))
    series = relative_scale_error(_scaled(gt, 0.37), gt, delta=1.0)
    assert series.errors.size == 200 - 20
    np.testing.assert_allclose(series.errors, 0.0, atol=1e-9)


def test_a_scale_jump_shows_as_the_ratio_of_the_two_halves():
    """The estimate moves 25 % further per step in its second half than the truth does."""
    gt = _line(np.full(200, 2.0))
    factor = np.where(np.arange(1, 200) < 100, 1.0, 1.25)[:, None]
    poses = gt.poses.copy()
    poses[1:, :3, 3] = np.cumsum(factor * np.diff(gt.positions, axis=0), axis=0)
    est = Trajectory(gt.timestamps, poses)
    series = relative_scale_error(est, gt, delta=1.0)
    first = series.errors[series.timestamps < 100 * 0.05]
    last = series.errors[series.timestamps >= (100 + 20) * 0.05]
    np.testing.assert_allclose(first, first[0], atol=1e-6)
    np.testing.assert_allclose(last, last[0], atol=1e-6)
    assert (1 + last[0]) / (1 + first[0]) == pytest.approx(1.25, abs=1e-3)
    assert first[0] < 0 < last[0]  # one alignment scale for the whole sub-map sits in between


def test_each_submap_uses_its_own_alignment_scale_and_hovering_is_left_out():
    speeds = np.concatenate([np.full(100, 2.0), np.zeros(40), np.full(100, 2.0)])
    gt = _line(speeds)
    submap = np.repeat([0, 1], [120, 120])
    poses = gt.poses.copy()
    poses[:120, :3, 3] *= 0.5
    poses[120:, :3, 3] *= 3.0
    series = relative_scale_error(Trajectory(gt.timestamps, poses, submap), gt, delta=1.0)
    np.testing.assert_allclose(series.errors, 0.0, atol=1e-9)
    hover = (series.timestamps > 101 * 0.05 + 1.0) & (series.timestamps < 140 * 0.05)
    assert not hover.any()  # no true motion over the last second: no ratio
    given = relative_scale_error(Trajectory(gt.timestamps, poses, submap), gt, 1.0, {0: 2.0})
    assert given.errors.size and np.all(given.timestamps < 120 * 0.05)  # sub-map 1 has no scale
    np.testing.assert_allclose(given.errors, 0.0, atol=1e-9)


def test_drift_rate_is_the_slope_of_the_log_scale():
    """The estimate's step length grows by the factor exp(r dt) per step: its log scale rises
    by r per second, which the drift rate recovers (independent of the alignment scale)."""
    dt, r = 0.05, 0.08
    gt = _line(np.full(300, 2.0), dt)
    factor = np.exp(r * dt * np.arange(1, 300))[:, None]
    poses = gt.poses.copy()
    poses[1:, :3, 3] = np.cumsum(factor * np.diff(gt.positions, axis=0), axis=0)
    series = relative_scale_error(Trajectory(gt.timestamps, poses), gt, delta=1.0)
    rate = scale_drift_rate(series, lag=1.0)
    assert rate.rates.size > 200
    np.testing.assert_allclose(rate.rates, r, rtol=1e-2)  # the path curves: step lengths vary a little
    flat = scale_drift_rate(relative_scale_error(_scaled(gt, 0.37), gt, delta=1.0), lag=1.0)
    np.testing.assert_allclose(flat.rates, 0.0, atol=1e-9)
