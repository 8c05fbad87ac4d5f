"""All metrics of one run: ATE, RPE (paper Eq. 18-20), the RPE with the alignment's fixed
scale, tracking percentage and restarts."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from granite.evaluation.ate import AteResult, ate
from granite.evaluation.association import check_nonempty
from granite.evaluation.rpe import DEFAULT_RPE_DELTA, RpeResult, rpe
from granite.evaluation.tracking import restart_count, tracking_percentage
from granite.geometry import interpolate_poses
from granite.trajectory import Trajectory


def overlap_path_length(est: Trajectory, gt: Trajectory) -> float:
    """Path length of the ground truth over the time span it shares with the estimate
    (ground-truth samples inside the span plus interpolated end points)."""
    lo = max(est.timestamps[0], gt.timestamps[0])
    hi = min(est.timestamps[-1], gt.timestamps[-1])
    if hi <= lo:
        return 0.0
    inner = (gt.timestamps > lo) & (gt.timestamps < hi)
    ends = interpolate_poses(gt.timestamps, gt.poses, np.array([lo, hi]))[:, :3, 3]
    pts = np.vstack([ends[:1], gt.positions[inner], ends[1:]])
    return float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else float(x)


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """Metrics of an estimate against the ground truth; :meth:`to_dict` is JSON-ready."""

    ate: AteResult
    rpe: RpeResult
    rpe_fixed_scale: RpeResult
    tracking_percentage: float
    restarts: int
    num_poses: int
    path_length: float
    align_frames: int | None = None

    def to_dict(self) -> dict[str, Any]:
        """Flat dictionary; undefined values (no RPE pair, zero path length) are ``None``."""
        a, r = self.ate, self.rpe
        return {
            "ate_rmse": a.rmse,
            "ate_mean": a.mean,
            "ate_median": a.median,
            "ate_max": a.max,
            "rpe_rmse": _num(r.rmse),
            "tracking_percentage": self.tracking_percentage,
            "restarts": self.restarts,
            "num_poses": self.num_poses,
            "num_ate_poses": a.num_poses,
            "num_rpe_pairs": r.num_pairs,
            "rpe_skipped_static": r.skipped_static,
            "rpe_skipped_submap": r.skipped_submap,
            "rpe_skipped_no_gt": r.skipped_no_gt,
            "path_length": self.path_length,
            "ate_over_path_length": (
                _num(a.rmse / self.path_length) if self.path_length > 0 else None
            ),
            "align": a.align,
            "align_frames": self.align_frames,
            "rpe_fixed_scale_rmse": _num(self.rpe_fixed_scale.rmse),
            "num_rpe_fixed_scale_pairs": self.rpe_fixed_scale.num_pairs,
            "delta": r.delta,
            "submap_scales": {str(k): v for k, v in a.scales.items()},
            "skipped_submaps": {str(k): v for k, v in a.skipped_submaps.items()},
        }


def evaluate(
    est: Trajectory, gt: Trajectory, delta: float = DEFAULT_RPE_DELTA, align: str = "sim3",
    align_frames: int | None = None,
) -> EvaluationResult:
    """ATE (``align`` per sub-map, estimated from all poses of a sub-map or its first
    ``align_frames``), RPE over ``delta`` s (Eq. 18-20, and with each sub-map's alignment
    scale fixed: scale drift counts), tracking percentage (over the estimate's time span),
    restart count, and the ground-truth path length over the overlap."""
    check_nonempty(est, gt)
    ate_result = ate(est, gt, align, align_frames)
    return EvaluationResult(
        ate=ate_result,
        rpe=rpe(est, gt, delta),
        rpe_fixed_scale=rpe(est, gt, delta, fixed_scales=ate_result.scales),
        align_frames=align_frames,
        tracking_percentage=tracking_percentage(est),
        restarts=restart_count(est),
        num_poses=len(est),
        path_length=overlap_path_length(est, gt),
    )
