"""Re-optimisation after outlier removal (``[estimator] outlier_reoptimize_iterations``): when
observations of the current frame are removed as outliers, the published pose is re-optimised
without them. Checked against the ground truth of two pre-rendered flights: per frame where it
acts, the pose before and after the extra iterations, relative to the previous published pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
import pytest

from granite.backend.window import SlidingWindow
from granite.estimator.config import VoConfig
from granite.estimator.vo import MonocularVO
from granite.geometry.interpolation import interpolate_poses
from granite.io import open_dataset

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "sequences"


def _rotation_error_deg(T_prev: np.ndarray, T: np.ndarray, T_rel_true: np.ndarray) -> float:
    R_rel = T_prev[:3, :3].T @ T[:3, :3]
    return float(np.degrees(Rotation.from_matrix(R_rel.T @ T_rel_true[:3, :3]).magnitude()))


def _run(root: Path, iterations: int, monkeypatch, min_fraction: float = 0.0,
         states: str = "pose"):
    """Run the VO; per tracked frame whose own observations lost outliers: (rotation error of
    the pose when the outliers were removed, rotation error of the published pose), degrees,
    against the true rotation from the previous frame. Also the number of optimisations (of
    the window or of one pose) that ran after an outlier removal."""
    calls = {"current": None, "removed": False, "pose_at_removal": None, "after_removal": 0}
    remove, optimize = SlidingWindow.remove_outliers, SlidingWindow.optimize
    refine = SlidingWindow.refine_pose

    def remove_outliers(self, *args, **kwargs):
        removed = remove(self, *args, **kwargs)
        frame = calls["current"]
        if frame is not None and frame in self and any(f == frame for _, f in removed):
            calls["removed"], calls["pose_at_removal"] = True, self.pose(frame).copy()
        return removed

    def optimize_(self, *args, **kwargs):
        if calls["removed"]:
            calls["after_removal"] += 1
        return optimize(self, *args, **kwargs)

    def refine_pose(self, *args, **kwargs):
        if calls["removed"]:
            calls["after_removal"] += 1
        return refine(self, *args, **kwargs)

    monkeypatch.setattr(SlidingWindow, "remove_outliers", remove_outliers)
    monkeypatch.setattr(SlidingWindow, "optimize", optimize_)
    monkeypatch.setattr(SlidingWindow, "refine_pose", refine_pose)
    ds = open_dataset(root)
    gt = ds.ground_truth

    def truth(t: float) -> np.ndarray:
        return interpolate_poses(gt.timestamps, gt.poses, np.array(t))
    cfg = VoConfig.from_dict({"estimator": {"outlier_reoptimize_iterations": iterations,
                                            "outlier_reoptimize_min_fraction": min_fraction,
                                            "outlier_reoptimize_states": states}})
    vo = MonocularVO(ds.calibration.camera(), cfg)
    errors, previous = [], None
    for i, frame in enumerate(ds.frames(0, len(ds))):
        calls.update(current=i, removed=False, pose_at_removal=None)
        out = vo.process(i, frame.timestamp, frame.image)
        calls["removed"] = False  # marginalisation of this frame is not an optimisation
        if previous is not None and calls["pose_at_removal"] is not None and out.diagnostics.state == "tracking":
            T_rel_true = np.linalg.inv(truth(previous[0])) @ truth(frame.timestamp)
            errors.append((_rotation_error_deg(previous[1], calls["pose_at_removal"], T_rel_true),
                           _rotation_error_deg(previous[1], out.T_w_c, T_rel_true)))
        previous = (frame.timestamp, out.T_w_c)
    return np.array(errors), calls["after_removal"]


@pytest.mark.parametrize("states, gain", [("pose", 0.9), ("window", 0.8)])
def test_the_published_pose_is_reoptimised_without_the_outliers_of_its_frame(monkeypatch, states,
                                                                            gain):
    default = VoConfig().estimator
    runs = [_run(ASSETS / name, default.outlier_reoptimize_iterations, monkeypatch,
                 default.outlier_reoptimize_min_fraction, states)
            for name in ("aggressive", "framedrop")]
    errors = np.concatenate([e for e, _ in runs])
    before, after = errors[:, 0], errors[:, 1]
    # measured: 24 frames, mean 0.063 -> 0.054 degrees, better in 88 % of them (the pose
    # alone); 23 frames, 0.060 -> 0.044, 87 % (the window)
    assert len(errors) >= 10
    assert after.mean() < gain * before.mean()
    assert np.mean(after < before) >= 0.7


@pytest.mark.parametrize("states", ["pose", "window"])
def test_without_the_option_nothing_is_optimised_after_the_outlier_removal(monkeypatch, states):
    errors, after_removal = _run(ASSETS / "aggressive", 0, monkeypatch, states=states)
    assert len(errors) > 0  # outliers of the current frame were removed ...
    assert after_removal == 0  # ... and nothing was optimised after that
    np.testing.assert_array_equal(errors[:, 0], errors[:, 1])  # published as it was


def test_a_small_share_of_outliers_does_not_trigger_it(monkeypatch):
    """With the share set above any frame's outlier share nothing is re-optimised."""
    errors, after_removal = _run(ASSETS / "aggressive", 2, monkeypatch, min_fraction=1.0)
    assert len(errors) > 0 and after_removal == 0


if __name__ == "__main__":  # print the measured figures
    mp = pytest.MonkeyPatch()
    d = VoConfig().estimator
    e = np.concatenate([_run(ASSETS / n, d.outlier_reoptimize_iterations, mp, d.outlier_reoptimize_min_fraction,
                             d.outlier_reoptimize_states)[0] for n in ("aggressive", "framedrop")])
    print(len(e), e.mean(axis=0), np.mean(e[:, 1] < e[:, 0]))
