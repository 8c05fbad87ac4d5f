"""Trajectory evaluation (pure algorithms on :class:`granite.trajectory.Trajectory`, no file
I/O): ATE with per-sub-map alignment, the paper's scale-free RPE (Eq. 18-20), tracking
percentage and restart count (Fig. 7, Table I), and the true relative scale error over
time (Fig. 4)."""

from granite.evaluation.association import associate
from granite.evaluation.ate import ALIGNMENTS, AteResult, align_poses, ate
from granite.evaluation.evaluate import EvaluationResult, evaluate, overlap_path_length
from granite.evaluation.rpe import DEFAULT_RPE_DELTA, RpeResult, rpe
from granite.evaluation.scale_drift import (
    ScaleDriftRate,
    ScaleErrorSeries,
    relative_scale_error,
    scale_drift_rate,
)
from granite.evaluation.tracking import longest_run_duration, restart_count, tracking_percentage

__all__ = [
    "ALIGNMENTS",
    "DEFAULT_RPE_DELTA",
    "AteResult",
    "EvaluationResult",
    "RpeResult",
    "ScaleErrorSeries",
    "align_poses",
    "associate",
    "ate",
    "evaluate",
    "longest_run_duration",
    "overlap_path_length",
    "relative_scale_error",
    "scale_drift_rate",
    "ScaleDriftRate",
    "restart_count",
    "rpe",
    "tracking_percentage",
]
