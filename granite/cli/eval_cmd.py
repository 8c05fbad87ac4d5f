"""``granite eval``: compare an estimated trajectory with the ground truth."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from granite.errors import InputError
from granite.evaluation.rpe import DEFAULT_RPE_DELTA

DESCRIPTION = """\
Evaluate an estimated trajectory against the ground truth, as in the paper (Sec. VI):

  ATE    RMSE of the position error after aligning every sub-map separately to the
         ground truth (Sim(3) by default, as needed for monocular scale ambiguity).
  RPE    RMS of the scale-free relative pose error over DELTA seconds (paper Eq. 18-20):
         only the direction of each relative motion counts; the first DELTA seconds and
         pairs spanning two sub-maps are excluded.
  RPE with fixed scale
         the same pairs with every relative motion scaled by its sub-map's ATE alignment
         scale instead of its own ratio (Eq. 19): errors of length, i.e. scale drift, count.
         With --align-frames 100 the scale is the one of the first 100 poses (paper Fig. 4).
  tracking percentage
         longest continuously tracked section (one sub-map) / estimate duration.
  restarts
         number of sub-map changes (tracking failures).

Sub-maps: each has its own origin and scale, so they are aligned and evaluated apart. They
come from --submaps FILE when given ('none': one sub-map), else from the 9th column of EST
(older granite runs), else from a submaps.csv beside EST (what `granite run` writes next to
its 8-column trajectory.tum); without any, EST is one sub-map (the output says which).

The ground truth is linearly interpolated (slerp for rotations) at the estimate's
timestamps. Errors are in ground-truth units (metres)."""

EPILOG = """\
file formats:
  EST  TUM file: 't tx ty tz qx qy qz qw [submap]' per line (seconds, T_w_c,
       Hamilton quaternion; optional 9th column = integer sub-map index), or a
       granite run folder (its trajectory.tum and submaps.csv).
  SUBMAPS  CSV 'timestamp,frame_index,submap', one row per pose of EST.
  GT   TUM file, or EuRoC ground-truth CSV ('timestamp [ns], p xyz, q wxyz, ...'),
       detected from the content. EuRoC poses are body (IMU) poses; pass --calib to
       convert them to camera poses with T_imu_cam.

examples:
  granite eval --est runs/demo/run --gt runs/demo/dataset/groundtruth.tum
  granite eval --est traj.tum --gt mav0/state_groundtruth_estimate0/data.csv \\
               --calib calib.json --delta 4 --json     # Δ = 4 s: the paper's MADMAX setting
  granite eval --est runs/spiral --gt spiral/groundtruth.tum --align-frames 100
                                                       # aligned on the first 100 poses (Fig. 4)"""


def positive_seconds(text: str) -> float:
    """argparse type: a positive, finite number of seconds."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds: {text!r}")
    return value


def int_at_least(minimum: int, unit: str = ""):
    """argparse type: an integer of at least ``minimum`` (``unit`` names it in the error)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}{unit}: {text!r}")
        return value
    return parse


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "eval",
        help="evaluate a trajectory (ATE, paper RPE, tracking percentage, restarts)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--est", required=True, type=Path, metavar="EST",
                        help="estimated trajectory (TUM, optional 9th sub-map column) or run folder")
    parser.add_argument("--gt", required=True, type=Path, metavar="GT",
                        help="ground truth (TUM file or EuRoC ground-truth CSV)")
    parser.add_argument("--submaps", metavar="SUBMAPS",
                        help="sub-map index per pose (CSV), or 'none' to evaluate EST as one "
                             "sub-map (default: automatic, see above)")
    parser.add_argument("--delta", type=positive_seconds, default=DEFAULT_RPE_DELTA, metavar="SECONDS",
                        help=f"RPE time offset in seconds (default: {DEFAULT_RPE_DELTA:g}, the same in "
                             "every granite command; the paper used 4 for 1 Hz ground truth)")
    parser.add_argument("--align", choices=("sim3", "se3", "none"), default="sim3",
                        help="ATE alignment per sub-map (default: sim3)")
    parser.add_argument("--align-frames", type=int_at_least(3, " poses"), default=None, metavar="N",
                        help="estimate each sub-map's alignment from its first N poses only and "
                             "apply it to the whole sub-map (paper Fig. 4: 100; at least 3; "
                             "default: all poses)")
    parser.add_argument("--calib", type=Path, metavar="CALIB",
                        help="Basalt calib.json whose T_imu_cam converts EuRoC body ground "
                             "truth to camera poses (ignored for TUM ground truth)")
    parser.add_argument("--json", action="store_true",
                        help="print exactly one JSON object instead of the table")
    return parser


def _fmt(value: float | None, unit: str = "", digits: int = 6) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}{unit}"


def format_table(result: dict[str, Any], est: Path, gt: Path) -> str:
    """Human-readable summary of :meth:`EvaluationResult.to_dict`."""
    r = result
    scales = ", ".join(f"{k}: {v:.6g}" for k, v in r["submap_scales"].items())
    ratio = r["ate_over_path_length"]
    rows = [
        ("estimate", f"{est} ({r['num_poses']} poses, {r['restarts'] + 1} sub-map runs)"),
        ("ground truth", str(gt)),
        ("sub-maps from", r.get("submaps_source", "-")),
        (f"ATE RMSE ({r['align']}, per sub-map"
         + ("" if r.get("align_frames") is None else f", aligned on the first {r['align_frames']} poses")
         + ")", _fmt(r["ate_rmse"], " m")),
        ("ATE mean / median / max",
         f"{_fmt(r['ate_mean'])} / {_fmt(r['ate_median'])} / {_fmt(r['ate_max'])} m"),
        ("ATE poses", str(r["num_ate_poses"])),
        (f"RPE RMSE (delta {r['delta']:g} s)", _fmt(r["rpe_rmse"], " m")),
        ("RPE pairs", f"{r['num_rpe_pairs']} (skipped: {r['rpe_skipped_static']} static, "
                      f"{r['rpe_skipped_submap']} across sub-maps, "
                      f"{r['rpe_skipped_no_gt']} outside ground truth)"),
        (f"RPE RMSE, fixed scale (delta {r['delta']:g} s)",
         f"{_fmt(r['rpe_fixed_scale_rmse'], ' m')} ({r['num_rpe_fixed_scale_pairs']} pairs, each sub-map's "
         "alignment scale)"),
        ("tracking percentage", f"{r['tracking_percentage']:.1f} %"),
        ("restarts", str(r["restarts"])),
        ("initialisation delay", "n/a (no diagnostics.csv)" if "init_delay_frames" not in r else
         f"{r['init_delay_frames']} frames / {_fmt(r['init_delay_s'], ' s', 3)} after "
         f"{r['init_min_baseline']:g} m of ground-truth baseline"),
        ("path length (ground truth)", _fmt(r["path_length"], " m", 3)),
        ("ATE / path length", "n/a" if ratio is None else f"{100 * ratio:.3f} %"),
        ("sub-map scales", scales or "-"),
    ]
    rows += [(f"skipped sub-map {k}", v) for k, v in r["skipped_submaps"].items()]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def run(args: argparse.Namespace) -> int:
    from granite.evaluation import evaluate
    from granite.io import read_calibration, read_estimate, read_trajectory

    T_body_cam = read_calibration(args.calib).T_imu_cam if args.calib is not None else None
    est, source = read_estimate(args.est, args.submaps)
    gt = read_trajectory(args.gt, T_body_cam)
    try:
        result = evaluate(est, gt, delta=args.delta, align=args.align, align_frames=args.align_frames).to_dict()
    except InputError as error:
        if error.path is None:  # name the estimate in errors of the pure algorithms
            raise InputError(error.message, args.est) from None
        raise
    result["submaps_source"] = source
    diagnostics = (args.est if args.est.is_dir() else args.est.parent) / "diagnostics.csv"
    if diagnostics.is_file():  # a run folder: the initialisation delay from its states
        from granite.estimator.diagnostics import read_diagnostics
        from granite.evaluation.initialization import initialization_delay

        rows = read_diagnostics(diagnostics)
        result.update(initialization_delay([d.timestamp for d in rows], [d.state for d in rows],
                                           gt).to_dict())
    if args.json:
        result = {"estimate": str(args.est), "ground_truth": str(args.gt), **result}
        print(json.dumps(result, allow_nan=False))
    else:
        print(format_table(result, args.est, args.gt))
    return 0
