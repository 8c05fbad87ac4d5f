"""``granite run``: the monocular VO over a dataset folder."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from granite.errors import GraniteError
from granite.estimator.config import VoConfig
from granite.estimator.records import FrameRecord, write_records
from granite.estimator.runner import run_vo, write_run
from granite.evaluation import evaluate
from granite.io import atomic_write_text, open_dataset

DESCRIPTION = """\
Run the monocular visual odometry over a dataset (EuRoC/ASL, TUM RGB-D, KITTI odometry or a
granite-sim test-bench folder) and write the run folder OUT:

  trajectory.tum    T_w_c of every frame, TUM text + 9th column = sub-map index
  diagnostics.csv   per frame: sub-map, state, tracks, finite/infinite landmarks, keyframe,
                    negative entropy, processing time
  keyframes.csv     keyframes (timestamp, frame index, sub-map)
  landmarks.npz     per-frame tracks with landmark inverse distances (for granite view)
  config.toml       the exact configuration used
  summary.json      counts and timing
  evaluation.json   ATE / RPE / tracking percentage / restarts, when ground truth exists

The configuration is a TOML file (see configs/mono_default.toml); missing keys take the
reference monocular defaults.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run", help="run the VO on a dataset", description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", type=Path, help="dataset folder")
    p.add_argument("--out", type=Path, required=True, help="run folder to write")
    p.add_argument("--config", type=Path, help="VO configuration (TOML)")
    p.add_argument("--calib", type=Path, help="Basalt calib.json overriding the dataset's calibration")
    p.add_argument("--max-frames", type=int, help="process only the first N frames")
    p.add_argument("--delta", type=float, default=1.0,
                   help="RPE delta in seconds for the evaluation (default: 1, for 20 Hz ground truth)")
    p.add_argument("--finest-level-only", action="store_true",
                   help="ablation †: detect corners on pyramid level 0 only")
    p.add_argument("--current-frame-keyframe", action="store_true",
                   help="ablation ‡: make the current (not the previous) frame the keyframe")
    viz = p.add_mutually_exclusive_group()
    viz.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="save a rerun recording")
    viz.add_argument("--spawn", action="store_true", help="stream live to a rerun viewer (needs a display)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def load_config(args) -> VoConfig:
    config = VoConfig.load(args.config) if args.config else VoConfig()
    if args.finest_level_only:
        config = dataclasses.replace(
            config, optical_flow=dataclasses.replace(config.optical_flow, detect_all_levels=False))
    if args.current_frame_keyframe:
        config = dataclasses.replace(
            config, estimator=dataclasses.replace(config.estimator, previous_frame_as_keyframe=False))
    return config


def perform_run(dataset, config: VoConfig, out: Path, rerun: Path | None = None, spawn: bool = False,
                delta: float = 1.0, max_frames: int | None = None, progress: bool = True):
    """Run the VO on an opened dataset, write the run folder; returns (result, evaluation dict
    or None)."""
    records: list[FrameRecord] = []
    view = None
    if rerun or spawn:
        from granite.visualization.run_view import RunView

        view = RunView(f"granite-run-{dataset.name}", dataset.calibration, dataset.ground_truth, rerun, spawn)

    def on_frame(frame, output):
        record = FrameRecord.from_output(frame.index, frame.timestamp, output)
        records.append(record)
        if view is not None:
            view.log_frame(record, frame.image, output.diagnostics, frame.path)

    result = run_vo(dataset, config, progress=progress, on_frame=on_frame, max_frames=max_frames)
    write_run(out, result, config, {"dataset": str(dataset.root), "format": dataset.format})
    write_records(out / "landmarks.npz", records)
    evaluation = None
    if dataset.ground_truth is not None:
        try:
            evaluation = evaluate(result.trajectory, dataset.ground_truth, delta=delta).to_dict()
        except GraniteError as error:  # the run itself succeeded: keep its outputs
            print(f"warning: evaluation skipped: {error}", file=sys.stderr)
        else:
            atomic_write_text(out / "evaluation.json", json.dumps(evaluation, indent=2) + "\n")
    if view is not None:
        view.finish(result.trajectory)
        result.logging_startup_seconds, result.logging_seconds = view.startup_seconds, view.seconds
    return result, evaluation


def summary_lines(result, evaluation: dict | None, delta: float) -> list[str]:
    lines = [f"{len(result.diagnostics)} frames, {len(result.skipped)} skipped, {result.restarts} restarts, "
             f"{len(result.keyframes)} keyframes"]
    if evaluation is not None:
        e = evaluation
        frac = e["ate_over_path_length"]
        rpe = "n/a" if e["rpe_rmse"] is None else f"{e['rpe_rmse']:.4f} m"
        lines.append(
            f"ATE (Sim3) {e['ate_rmse']:.4f} m"
            + (f" ({100 * frac:.2f} % of {e['path_length']:.1f} m)" if frac is not None else "")
            + f", RPE({delta:g} s) {rpe}, tracking {e['tracking_percentage']:.1f} %"
        )
    return lines


def run(args) -> int:
    config = load_config(args)
    dataset = open_dataset(args.dataset, calib_path=args.calib)
    result, evaluation = perform_run(dataset, config, args.out, args.rerun, args.spawn, args.delta,
                                     args.max_frames, progress=not args.quiet)
    for line in summary_lines(result, evaluation, args.delta):
        print(line)
    print(f"outputs: {args.out}")
    if result.interrupted:
        print("interrupted: the outputs hold the frames processed so far", file=sys.stderr)
        return 130
    return 0
