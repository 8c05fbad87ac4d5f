"""Evaluation metrics: ATE (cross-checked with evo), the paper's RPE (analytic cases and a
brute-force loop reference with scipy's Slerp), tracking percentage and restarts."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from granite.errors import InputError
from granite.evaluation import (
    ate,
    evaluate,
    longest_run_duration,
    restart_count,
    rpe,
    tracking_percentage,
)
from granite.io import write_tum
from granite.trajectory import Trajectory

# --------------------------------------------------------------------------- helpers


def make_poses(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(p), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    return T


def smooth_motion(rng: np.random.Generator, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (N,3,3) and positions (N,3) of a random smooth 3-D motion."""
    amp = rng.uniform(0.5, 3.0, size=(3, 3))
    freq = rng.uniform(0.03, 0.2, size=(3, 3))
    phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
    vel = rng.normal(size=3)
    waves = np.sin(2 * np.pi * freq * t[:, None, None] + phase)
    p = vel * t[:, None] + np.einsum("ak,nak->na", amp, waves)
    rv = 0.6 * waves[:, 1, :] + 0.1 * t[:, None] * rng.normal(size=3)
    return Rotation.from_rotvec(rv).as_matrix(), p


def rot(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


def sim3_transform(poses: np.ndarray, s: float, R0: np.ndarray, t0: np.ndarray) -> np.ndarray:
    """Apply x -> s R0 x + t0 to the world frame of camera poses."""
    return make_poses(R0 @ poses[:, :3, :3], s * poses[:, :3, 3] @ R0.T + t0)


def noisy_estimate(rng, gt_poses, s, R0, t0, sigma_p=0.05, sigma_r=0.01):
    est = sim3_transform(gt_poses, s, R0, t0)
    est[:, :3, 3] += rng.normal(scale=sigma_p * s, size=(len(est), 3))
    noise = Rotation.from_rotvec(rng.normal(scale=sigma_r, size=(len(est), 3))).as_matrix()
    est[:, :3, :3] = est[:, :3, :3] @ noise
    return est


# --------------------------------------------------------------------------- ATE vs evo


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("align", ["sim3", "se3"])
def test_ate_matches_evo(tmp_path: Path, seed: int, align: str) -> None:
    from evo.core import sync
    from evo.core.metrics import PoseRelation
    from evo.main_ape import ape
    from evo.tools import file_interface

    rng = np.random.default_rng(seed)
    t_gt = 1.5e9 + np.arange(300) * 0.05
    gt = Trajectory(t_gt, make_poses(*smooth_motion(rng, t_gt - t_gt[0])))
    keep = np.sort(rng.choice(np.arange(10, 290), size=150, replace=False))  # est ⊂ gt times
    s = float(rng.uniform(0.2, 5.0))
    R0 = Rotation.random(random_state=seed).as_matrix()
    t0 = rng.normal(scale=10, size=3)
    est = Trajectory(t_gt[keep], noisy_estimate(rng, gt.poses[keep], s, R0, t0))
    write_tum(tmp_path / "gt.tum", gt)  # with the '#' header line: evo skips it
    write_tum(tmp_path / "est.tum", est)

    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    e = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    ref, e = sync.associate_trajectories(ref, e)
    res = ape(ref, e, PoseRelation.translation_part, align=True, correct_scale=(align == "sim3"))

    ours = ate(est, gt, align)
    assert ours.num_poses == len(keep) == res.np_arrays["error_array"].size
    assert ours.rmse == pytest.approx(res.stats["rmse"], abs=1e-6)
    assert ours.mean == pytest.approx(res.stats["mean"], abs=1e-6)
    assert ours.median == pytest.approx(res.stats["median"], abs=1e-6)
    assert ours.max == pytest.approx(res.stats["max"], abs=1e-6)
    assert ours.rmse > 1e-3  # the noise is visible: the comparison is not trivially 0 == 0
    if align == "sim3":
        assert ours.scales[0] == pytest.approx(1 / s, rel=0.05)


def test_ate_none_is_raw_position_error() -> None:
    t = np.arange(20.0)
    R, p = smooth_motion(np.random.default_rng(0), t)
    gt = Trajectory(t, make_poses(R, p))
    est = Trajectory(t, make_poses(R, p + np.array([0.0, 3.0, 4.0])))
    assert ate(est, gt, "none").rmse == pytest.approx(5.0, abs=1e-12)
    assert ate(est, gt, "se3").rmse == pytest.approx(0.0, abs=1e-9)


def test_per_submap_alignment_recovers_two_scales_exactly() -> None:
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 40.0, 401)
    gt = Trajectory(t, make_poses(*smooth_motion(rng, t)))
    sub = (t >= 18.0).astype(int)
    est_poses = np.empty_like(gt.poses)
    a = sub == 0
    est_poses[a] = sim3_transform(gt.poses[a], 0.5, rot(1), np.array([1.0, 2, 3]))
    est_poses[~a] = sim3_transform(gt.poses[~a], 3.0, rot(2), np.array([-5.0, 0, 9]))
    est = Trajectory(t, est_poses, sub)
    res = ate(est, gt, "sim3")
    assert res.rmse < 1e-9
    assert res.scales[0] == pytest.approx(2.0, rel=1e-9)
    assert res.scales[1] == pytest.approx(1.0 / 3.0, rel=1e-9)
    assert np.allclose(res.aligned.poses, gt.poses, atol=1e-8)
    assert np.array_equal(res.aligned.submap, sub)
    # The per-sub-map similarity maps the estimate's positions onto the ground truth.
    for sid, mask in ((0, a), (1, ~a)):
        s, R, t_ = res.transforms[sid]
        mapped = s * est_poses[mask, :3, 3] @ R.T + t_
        assert np.allclose(mapped, gt.poses[mask, :3, 3], atol=1e-8)
    # Aligning both sub-maps with one similarity cannot explain two scales.
    assert ate(Trajectory(t, est_poses), gt, "sim3").rmse > 0.1


def test_ate_skips_degenerate_submap() -> None:
    t = np.linspace(0.0, 10.0, 101)
    gt = Trajectory(t, make_poses(*smooth_motion(np.random.default_rng(3), t)))
    sub = np.zeros(101, dtype=int)
    sub[-2:] = 1  # two poses: alignment undetermined
    res = ate(Trajectory(t, gt.poses, sub), gt, "sim3")
    assert list(res.skipped_submaps) == [1]
    assert res.num_poses == 99


def test_no_time_overlap_raises() -> None:
    t = np.arange(10.0)
    poses = make_poses(np.tile(np.eye(3), (10, 1, 1)), np.c_[t, t**2, 0 * t])
    with pytest.raises(InputError, match="does not overlap the ground truth"):
        ate(Trajectory(t + 100.0, poses), Trajectory(t, poses))
    with pytest.raises(InputError, match="does not overlap"):
        evaluate(Trajectory(t + 100.0, poses), Trajectory(t, poses))


# --------------------------------------------------------------------------- RPE


def test_rpe_zero_for_scaled_rigidly_transformed_copy() -> None:
    rng = np.random.default_rng(11)
    t_gt = np.linspace(0.0, 30.0, 31)  # 1 Hz ground truth, like MADMAX
    gt = Trajectory(t_gt, make_poses(*smooth_motion(rng, t_gt)))
    # Estimate times include the ground truth's knots, so the estimate's own piecewise
    # interpolation at t - delta reproduces the ground truth's.
    t_est = np.union1d(t_gt, rng.uniform(0.0, 30.0, size=170))
    from granite.geometry import interpolate_poses

    copy = interpolate_poses(t_gt, gt.poses, t_est)
    sub = (t_est > 15.0).astype(int)
    est_poses = np.empty_like(copy)
    est_poses[sub == 0] = sim3_transform(copy[sub == 0], 0.3, rot(3), np.ones(3))
    est_poses[sub == 1] = sim3_transform(copy[sub == 1], 7.0, rot(4), -np.ones(3))
    res = rpe(Trajectory(t_est, est_poses, sub), gt, delta=4.0)
    assert res.num_pairs > 100
    assert res.rmse < 1e-9
    assert res.skipped_submap > 0


@pytest.mark.parametrize("theta", [0.05, 0.3])
def test_rpe_known_heading_error(theta: float) -> None:
    """Straight line at constant speed v along camera x; the estimate's orientations are
    right-multiplied by a yaw R_off about camera z and its positions scaled by k. Then
    trans(dT) = k R_off^T trans(dQ), s = 1/k, and every pair has the error
    |R_off^T d - d| = 2 sin(theta/2) |d| with |d| = v delta."""
    v, delta, k = 1.5, 2.0, 0.37
    R_c = Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix()  # fixed camera attitude
    t_gt = np.arange(0.0, 21.0, 1.0)
    gt_R = np.tile(R_c, (len(t_gt), 1, 1))
    gt = Trajectory(t_gt, make_poses(gt_R, v * t_gt[:, None] * R_c[:, 0]))  # along camera x
    rng = np.random.default_rng(5)
    t_est = np.sort(rng.uniform(0.5, 20.0, size=150))
    R_off = Rotation.from_euler("z", theta).as_matrix()
    est_R = np.tile(R_c @ R_off, (150, 1, 1))
    est = Trajectory(t_est, make_poses(est_R, k * v * t_est[:, None] * R_c[:, 0]))
    res = rpe(est, gt, delta=delta)
    expected = 2 * math.sin(theta / 2) * v * delta
    assert res.num_pairs == int(np.sum(t_est >= t_est[0] + delta))
    assert res.rmse == pytest.approx(expected, rel=1e-9)
    assert np.allclose(res.errors, expected, rtol=1e-9)
    assert np.allclose(res.scales, 1 / k, rtol=1e-9)


def brute_force_rpe(est_t, est_T, est_sub, gt_t, gt_T, delta):
    """Eq. 18-20 with plain loops, np.interp and scipy's Slerp."""

    def interp(ts, Ts, tq):
        pos = [np.interp(tq, ts, Ts[:, i, 3]) for i in range(3)]
        rot = Slerp(ts, Rotation.from_matrix(Ts[:, :3, :3]))([tq]).as_matrix()[0]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rot, pos
        return T

    sq = []
    for i in range(len(est_t)):
        t = est_t[i]
        if t < est_t[0] + delta:
            continue
        run = [j for j in range(len(est_t)) if est_sub[j] == est_sub[i]]  # contiguous in this test
        if t - delta < est_t[run[0]] or t - delta < gt_t[0] or t > gt_t[-1]:
            continue
        T_prev = interp(est_t[run], est_T[run], t - delta)
        dT = np.linalg.inv(T_prev) @ est_T[i]
        dQ = np.linalg.inv(interp(gt_t, gt_T, t - delta)) @ interp(gt_t, gt_T, t)
        s = np.linalg.norm(dQ[:3, 3]) / np.linalg.norm(dT[:3, 3])
        sq.append(np.sum((s * dT[:3, 3] - dQ[:3, 3]) ** 2))
    return math.sqrt(sum(sq) / len(sq)), len(sq)


@pytest.mark.parametrize("seed", [21, 22])
def test_rpe_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t_gt = np.arange(0.0, 40.0, 0.5) + 3.0
    gt = Trajectory(t_gt, make_poses(*smooth_motion(rng, t_gt)))
    t_est = np.sort(rng.uniform(1.0, 44.0, size=160))  # overhangs the ground truth at both ends
    from granite.geometry import interpolate_poses

    inside = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
    base = gt.poses[np.zeros(len(t_est), dtype=int)].copy()
    base[inside] = interpolate_poses(t_gt, gt.poses, t_est[inside])
    base[t_est > t_gt[-1]] = gt.poses[-1]
    sub = np.searchsorted([14.0, 29.0], t_est)
    est_T = noisy_estimate(rng, base, 2.5, rot(seed), np.zeros(3), 0.1, 0.05)
    est_T[sub == 2, :3, 3] += 0.3 * np.arange(np.sum(sub == 2))[:, None] * np.array([1.0, 0, 0])
    est = Trajectory(t_est, est_T, sub)
    expected, count = brute_force_rpe(t_est, est_T, sub, t_gt, gt.poses, 3.0)
    res = rpe(est, gt, delta=3.0)
    assert res.num_pairs == count > 50
    assert res.rmse == pytest.approx(expected, rel=1e-9)
    assert res.rmse > 0.01
    assert res.skipped_no_gt > 0 and res.skipped_submap > 0


def test_rpe_skips_and_counts_static_pairs() -> None:
    t = np.arange(0.0, 12.0)
    p = np.c_[np.minimum(t, 5.0), 0 * t, 0 * t]  # moves for 5 s, then hovers
    poses = make_poses(np.tile(np.eye(3), (12, 1, 1)), p)
    res = rpe(Trajectory(t, poses), Trajectory(t, poses), delta=2.0)
    # pairs t = 2..11; static (|dQ| = |dT| = 0) for t - 2 >= 5, i.e. t = 7..11
    assert res.skipped_static == 5
    assert res.num_pairs == 5
    assert res.rmse == pytest.approx(0.0, abs=1e-12)


def test_rpe_without_pairs_is_nan() -> None:
    t = np.arange(0.0, 3.0)
    poses = make_poses(np.tile(np.eye(3), (3, 1, 1)), np.c_[t, t, t])
    res = rpe(Trajectory(t, poses), Trajectory(t, poses), delta=4.0)
    assert res.num_pairs == 0 and math.isnan(res.rmse)
    with pytest.raises(ValueError):
        rpe(Trajectory(t, poses), Trajectory(t, poses), delta=0.0)


# --------------------------------------------------------------------------- tracking


def traj_with_submaps(t, sub) -> Trajectory:
    n = len(t)
    submap = None if sub is None else np.asarray(sub)
    return Trajectory(np.asarray(t, float), np.tile(np.eye(4), (n, 1, 1)), submap)


def test_tracking_percentage_and_restarts() -> None:
    est = traj_with_submaps(np.arange(45.0), [0] * 10 + [1] * 30 + [2] * 5)
    assert longest_run_duration(est) == 29.0
    assert tracking_percentage(est) == pytest.approx(100 * 29 / 44)
    assert restart_count(est) == 2
    assert tracking_percentage(est, span=(0.0, 58.0)) == pytest.approx(50.0)


def test_tracking_with_gap_and_repeated_ids() -> None:
    # no poses between 4 s and 10 s (lost); the longest run is 10 .. 20
    gap = traj_with_submaps(list(range(0, 5)) + list(range(10, 21)), [0] * 5 + [1] * 11)
    assert tracking_percentage(gap) == pytest.approx(50.0)
    rep = traj_with_submaps(np.arange(6.0), [0, 0, 1, 1, 0, 0])
    assert restart_count(rep) == 2
    assert tracking_percentage(rep) == pytest.approx(20.0)


def test_tracking_without_submaps() -> None:
    est = traj_with_submaps(np.arange(5.0), None)
    assert tracking_percentage(est) == 100.0
    assert restart_count(est) == 0


# --------------------------------------------------------------------------- evaluate


def test_evaluate_dict_on_exact_monocular_copy() -> None:
    t = np.linspace(0.0, 20.0, 201)
    R = Rotation.from_rotvec(np.c_[0 * t, 0 * t, 0.1 * t]).as_matrix()
    gt = Trajectory(t, make_poses(R, np.c_[0.5 * t, np.sin(t), 0 * t]))  # not collinear
    est = Trajectory(t, sim3_transform(gt.poses, 0.25, rot(9), np.ones(3)))
    d = evaluate(est, gt, delta=4.0, align="sim3").to_dict()
    for key in ("ate_rmse", "rpe_rmse", "tracking_percentage", "restarts", "num_poses",
                "num_rpe_pairs", "path_length", "ate_over_path_length", "align", "delta"):
        assert key in d
    assert d["ate_rmse"] < 1e-9 and d["rpe_rmse"] < 1e-9
    assert d["tracking_percentage"] == 100.0 and d["restarts"] == 0
    assert d["num_poses"] == 201
    assert d["num_rpe_pairs"] == 161  # t = 4.0 .. 20.0 at 0.1 s
    # path length of (0.5 t, sin t) over 0..20 s: integral of sqrt(0.25 + cos^2 t)
    from scipy.integrate import quad

    expected = quad(lambda x: math.sqrt(0.25 + math.cos(x) ** 2), 0, 20, limit=200)[0]
    assert d["path_length"] == pytest.approx(expected, rel=1e-3)
    assert d["align"] == "sim3" and d["delta"] == 4.0


def test_collinear_path_is_aligned_with_orientations() -> None:
    """A straight leg followed by a turn in place: positions are collinear, so the rotation
    about the line comes from the orientations; a known Sim(3) is recovered exactly."""
    t = np.linspace(0.0, 10.0, 101)
    p = np.c_[np.minimum(t, 5.0), 0 * t, 0 * t]  # leg along x, then standing still
    yaw = np.where(t > 5.0, (t - 5.0) * 0.6, 0.0)
    R = np.stack([rot_z(y) for y in yaw])
    gt = Trajectory(t, make_poses(R, p))
    est_poses = sim3_transform(gt.poses, 0.25, rot(3), np.array([2.0, -1.0, 0.5]))
    res = ate(Trajectory(t, est_poses), gt, "sim3")
    assert res.rmse < 1e-9
    assert res.scales[0] == pytest.approx(4.0, rel=1e-9)
    assert not res.skipped_submaps


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- Fig. 4 evaluation


def drifting_estimate(seed: int, jump: int, factor: float):
    """Ground truth (smooth 3-D motion, 20 Hz) and an estimate that is its similarity copy
    (world x -> s R0 x + t0) whose steps after pose ``jump`` are ``factor`` times longer."""
    rng = np.random.default_rng(seed)
    t = np.arange(300) * 0.05
    R, p = smooth_motion(rng, t)
    gt = make_poses(R, p)
    steps = np.diff(p, axis=0) * np.where(np.arange(1, len(t)) <= jump, 1.0, factor)[:, None]
    drifted = make_poses(R, np.vstack([p[:1], p[0] + np.cumsum(steps, axis=0)]))
    s, R0, t0 = 0.3, rot(seed), rng.normal(size=3)
    return Trajectory(t, gt), Trajectory(t, sim3_transform(drifted, s, R0, t0)), p, s


@pytest.mark.parametrize("seed", [3, 4])
def test_alignment_on_the_first_frames_keeps_the_drift_after_them(seed: int) -> None:
    """Aligned on the first 100 poses (exact up to the similarity), the estimate is exact there
    and off by 25 % of the true distance from pose 100 afterwards; a fit on all poses spreads
    that error over the whole flight and changes the scale."""
    gt, est, p, s = drifting_estimate(seed, jump=100, factor=1.25)
    first = ate(est, gt, "sim3", align_frames=100)
    assert first.scales[0] == pytest.approx(1 / s, rel=1e-9)
    expected = np.r_[np.zeros(100), 0.25 * np.linalg.norm(p[100:] - p[100], axis=1)]
    np.testing.assert_allclose(first.errors, expected, atol=1e-9)
    whole = ate(est, gt, "sim3")
    assert whole.errors[:100].max() > 1e-3 and abs(whole.scales[0] * s - 1) > 1e-3
    with pytest.raises(ValueError, match="at least 3"):
        ate(est, gt, "sim3", align_frames=2)


@pytest.mark.parametrize("seed", [3, 4])
def test_rpe_with_the_alignment_scale_counts_the_scale_drift_that_eq19_hides(seed: int) -> None:
    gt, est, p, s = drifting_estimate(seed, jump=100, factor=1.25)
    scales = ate(est, gt, "sim3", align_frames=100).scales
    eq19 = rpe(est, gt, 1.0)
    fixed = rpe(est, gt, 1.0, fixed_scales=scales)
    assert fixed.fixed_scale and not eq19.fixed_scale
    np.testing.assert_array_equal(fixed.timestamps, est.timestamps[20:])  # static pairs kept
    after = fixed.timestamps >= 120 * 0.05 - 1e-9  # both ends past the jump
    before = fixed.timestamps <= 100 * 0.05 + 1e-9
    k = np.flatnonzero(after) + 20
    np.testing.assert_allclose(fixed.errors[after], 0.25 * np.linalg.norm(p[k] - p[k - 20], axis=1), rtol=1e-9)
    np.testing.assert_allclose(fixed.errors[before], 0.0, atol=1e-9)
    np.testing.assert_array_equal(eq19.timestamps, fixed.timestamps)
    # each pair rescaled: nothing is left of the drift but the bend of the pairs across the jump
    np.testing.assert_allclose(eq19.errors[before | after], 0.0, atol=1e-9)
    assert eq19.rmse < 0.2 * fixed.rmse
    assert fixed.rmse > 0.1
    unaligned = rpe(est, gt, 1.0, fixed_scales={})
    assert unaligned.num_pairs == 0 and unaligned.skipped_unaligned == 280 and math.isnan(unaligned.rmse)


def test_evaluate_reports_the_fixed_scale_rpe_and_the_alignment_window() -> None:
    gt, est, p, s = drifting_estimate(5, jump=100, factor=1.25)
    d = evaluate(est, gt, 1.0, "sim3", align_frames=100).to_dict()
    assert d["align_frames"] == 100
    assert d["rpe_rmse"] < 0.2 * d["rpe_fixed_scale_rmse"]
    assert d["rpe_fixed_scale_rmse"] == pytest.approx(rpe(est, gt, 1.0, fixed_scales={0: 1 / s}).rmse, rel=1e-9)
    assert d["num_rpe_fixed_scale_pairs"] == 280
    assert evaluate(est, gt, 1.0, "sim3").to_dict()["align_frames"] is None
