"""``granite run``: the monocular VO over a dataset folder."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from granite.cli.eval_cmd import int_at_least, positive_seconds
from granite.errors import GraniteError
from granite.estimator.config import VoConfig
from granite.estimator.records import FrameRecord, RecordWriter, write_records
from granite.estimator.runner import TRAJECTORY_FORMATS, RunResult, run_vo, summary_dict, write_run
from granite.evaluation import DEFAULT_RPE_DELTA, evaluate
from granite.evaluation.initialization import initialization_delay
from granite.io import atomic_write_text, check_writable, open_dataset

DESCRIPTION = f"""\
Run the monocular visual odometry over a dataset (EuRoC/ASL, TUM RGB-D, KITTI odometry or a
granite-sim test-bench folder) and write the run folder OUT:

  trajectory.tum    T_w_c of every estimated frame, plain 8-column TUM (evo reads it);
                    skipped (unreadable, blank) frames are left out
  submaps.csv       timestamp, frame index, sub-map of every pose of trajectory.tum
  trajectory.kitti  with --format kitti: the same poses as KITTI rows (3x4, row-major)
  diagnostics.csv   per frame (skipped ones included): sub-map, state, tracks,
                    finite/infinite landmarks, keyframe, negative entropy, time, warnings
  keyframes.csv     keyframes (timestamp, frame index, sub-map)
  landmarks.npz     per-frame tracks with landmark inverse distances (for granite view)
  config.toml       the exact configuration used
  summary.json      counts, skipped frames by reason, warnings by kind, timing
  evaluation.json   with ground truth: ATE / RPE / tracking percentage / restarts
                    (not written when the evaluation fails; summary.json says why)
  *.png, report.md  plots (trajectory, translation error and scale error need ground
                    truth; points always) and a report showing them with the metrics

The configuration is a TOML file: configs/mono_default.toml documents the defaults (the
reference's values plus our additions, marked), configs/reference.toml is the reference
configuration. The ablation switches apply to either. The RPE uses Δ = {DEFAULT_RPE_DELTA:g} s
unless --delta says otherwise (the same default in every granite command). Bad input (options,
configuration, dataset, an output folder that cannot be written) is one error line and exit
status 2 before any work; Ctrl-C writes the frames processed so far and exits with 130.
"""


positive_int = int_at_least(1)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run", help="run the VO on a dataset", description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("dataset", type=Path, help="dataset folder")
    p.add_argument("--out", type=Path, required=True, help="run folder to write")
    p.add_argument("--config", type=Path, help="VO configuration (TOML; default: the built-in defaults "
                   "= configs/mono_default.toml; configs/reference.toml = the reference's)")
    p.add_argument("--calib", type=Path, help="Basalt calib.json overriding the dataset's calibration")
    p.add_argument("--max-frames", type=positive_int, metavar="N", help="process only the first N frames")
    p.add_argument("--delta", type=positive_seconds, default=DEFAULT_RPE_DELTA, metavar="SECONDS",
                   help=f"RPE delta in seconds for the evaluation and the scale-error plot "
                        f"(default: {DEFAULT_RPE_DELTA:g}, as in granite eval)")
    p.add_argument("--format", choices=TRAJECTORY_FORMATS, default="tum",
                   help="trajectory format besides trajectory.tum (always written): kitti adds "
                        "trajectory.kitti (default: tum only)")
    p.add_argument("--finest-level-only", action="store_true",
                   help="ablation †: detect corners on pyramid level 0 only")
    p.add_argument("--current-frame-keyframe", action="store_true",
                   help="ablation ‡: make the current (not the previous) frame the keyframe")
    viz = p.add_mutually_exclusive_group()
    viz.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="save a rerun recording")
    viz.add_argument("--spawn", action="store_true", help="stream live to a rerun viewer (needs a display)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--sequential", action="store_true",
                   help="one frame after the other on one thread (debugging; the default runs the "
                        "frontend of the next frame concurrently, with bit-identical results)")
    return p


def config_name(args) -> str:
    """How the configuration was chosen (recorded in summary.json and the report)."""
    name = str(args.config) if getattr(args, "config", None) else "built-in defaults (configs/mono_default.toml)"
    ablations = [s for flag, s in (("finest_level_only", "†"), ("current_frame_keyframe", "‡"))
                 if getattr(args, flag, False)]
    return name + (f" with ablation {' '.join(ablations)}" if ablations else "")


def apply_ablations(config: VoConfig, finest_level_only: bool = False,
                    current_frame_keyframe: bool = False) -> VoConfig:
    """``config`` with the paper's ablations switched on: † corners on the finest level only,
    ‡ the current (not the previous) frame made keyframe."""
    if finest_level_only:
        config = dataclasses.replace(
            config, optical_flow=dataclasses.replace(config.optical_flow, detect_all_levels=False))
    if current_frame_keyframe:
        config = dataclasses.replace(
            config, estimator=dataclasses.replace(config.estimator, previous_frame_as_keyframe=False))
    return config


def load_config(args) -> VoConfig:
    """The configuration file (or the defaults) with the ablation switches applied."""
    config = VoConfig.load(args.config) if args.config else VoConfig()
    return apply_ablations(config, args.finest_level_only, args.current_frame_keyframe)


def perform_run(dataset, config: VoConfig, out: Path, rerun: Path | None = None, spawn: bool = False,
                delta: float = DEFAULT_RPE_DELTA, max_frames: int | None = None, progress: bool = True,
                formats: tuple[str, ...] = ("tum",), config_label: str = "", report: bool = True,
                notify=None, concurrent: bool = True):
    """Run the VO on an opened dataset and write the run folder (with plots and ``report.md``
    when ``report``). Returns (result, evaluation dict or None); a failed evaluation leaves
    ``result.evaluation_error`` set and no ``evaluation.json``."""
    records: list[RecordWriter] = []  # landmarks.npz, streamed to disk: memory flat in the run's length
    view = None
    if rerun or spawn:
        from granite.visualization.run_view import RunView

        view = RunView(f"granite-run-{dataset.name}", dataset.calibration, dataset.ground_truth, rerun, spawn,
                       scale_delta=delta)

    def on_frame(frame, output):
        record = FrameRecord.from_output(frame.index, frame.timestamp, output)
        if not records:
            records.append(RecordWriter(out / "landmarks.npz"))
        records[0].append(record)
        if view is not None:
            view.log_frame(record, frame.image, output.diagnostics, frame.path)

    try:  # an error leaves neither landmarks.npz nor the recording behind
        result = run_vo(dataset, config, progress=progress, on_frame=on_frame, max_frames=max_frames,
                        notify=notify, concurrent=concurrent)
        evaluation = None
        if dataset.ground_truth is not None:
            try:
                evaluation = evaluate(result.trajectory, dataset.ground_truth, delta=delta).to_dict()
                evaluation.update(initialization_delay([d.timestamp for d in result.diagnostics],
                                                       [d.state for d in result.diagnostics],
                                                       dataset.ground_truth).to_dict())
            except (GraniteError, ValueError) as error:  # the run itself succeeded: keep its outputs
                result.evaluation_error = str(error)
                print(f"granite: warning: evaluation failed, no evaluation.json written: {error}", file=sys.stderr)
        extra = {"dataset": str(dataset.root), "format": dataset.format, "config": config_label or "given",
                 "rpe_delta": delta, "evaluation_error": result.evaluation_error,
                 "undistortion": dataset.undistortion.describe() if dataset.undistortion is not None else None}
        write_run(out, result, config, extra, formats)
        (out / "evaluation.json").unlink(missing_ok=True)
        if evaluation is not None:
            atomic_write_text(out / "evaluation.json", json.dumps(evaluation, indent=2, allow_nan=False) + "\n")
        if records:
            records[0].close()
        else:
            write_records(out / "landmarks.npz", [])
        if report:
            write_run_report(out, result, dataset, evaluation, delta, config_label or "given",
                             title=f"granite run: {dataset.name}")
        if view is not None:
            view.finish(result.trajectory)
            result.logging_startup_seconds, result.logging_seconds = view.startup_seconds, view.seconds
    except BaseException:
        for writer in records:
            writer.discard()
        if view is not None:
            view.discard()
        raise
    return result, evaluation


def write_run_report(out: Path, result: RunResult, dataset, evaluation: dict | None, delta: float,
                     config_label: str, title: str, header: tuple[str, ...] = (),
                     copies: tuple[tuple[Path, str], ...] = ()) -> None:
    """Plots and ``report.md`` of a run folder; ``copies``: more (path, image prefix) places to
    write the same report (e.g. the demo's top-level report, linking ``run/*.png``)."""
    from granite.visualization.report import report_markdown, write_plots, write_report

    plots = write_plots(out, result.trajectory, result.diagnostics, [t for t, _, _ in result.keyframes],
                        dataset.ground_truth, delta)
    camera = () if dataset.undistortion is None else (f"camera: {dataset.undistortion.describe()}",)
    header = (f"dataset: `{dataset.root}` ({len(dataset)} images, format {dataset.format})", *camera,
              f"configuration: {config_label}", f"run folder: `{out}`", *header)
    summary = summary_dict(result)
    write_report(out / "report.md", report_markdown(title, header, summary, evaluation,
                                                     result.evaluation_error, plots))
    for path, prefix in copies:
        write_report(path, report_markdown(title, header, summary, evaluation, result.evaluation_error,
                                           plots, prefix))


def summary_lines(result, evaluation: dict | None, delta: float) -> list[str]:
    lines = [f"{len(result.diagnostics)} frames, {len(result.skipped)} skipped, {result.restarts} restarts, "
             f"{len(result.keyframes)} keyframes"]
    numerical = result.tally.numerical()
    if numerical:
        lines.append(f"{sum(k.count for k in numerical)} warnings of {len(numerical)} kind(s), see summary.json")
    if evaluation is not None:
        e = evaluation
        frac = e["ate_over_path_length"]
        rpe = "n/a" if e["rpe_rmse"] is None else f"{e['rpe_rmse']:.4f} m"
        lines.append(
            f"ATE (Sim3) {e['ate_rmse']:.4f} m"
            + (f" ({100 * frac:.2f} % of {e['path_length']:.1f} m)" if frac is not None else "")
            + f", RPE({delta:g} s) {rpe}, tracking {e['tracking_percentage']:.1f} %"
        )
        if "init_delay_frames" in e:
            delay = e["init_delay_frames"]
            lines.append("map never initialised" if delay is None else
                         f"map initialised {delay} frames ({e['init_delay_s']:.2f} s) after "
                         f"{e['init_min_baseline']:g} m of ground-truth baseline")
    elif result.evaluation_error is not None:
        lines.append(f"evaluation failed: {result.evaluation_error}")
    return lines


def cli_notifier(command: str):
    """One stderr line per first warning of a kind, above the progress bar."""
    from tqdm import tqdm

    return lambda text: tqdm.write(f"granite {command}: warning: {text}", file=sys.stderr)


def check_outputs(args) -> None:
    """Unwritable outputs are one error line before any work."""
    check_writable(args.out)
    if getattr(args, "rerun", None):
        check_writable(args.rerun, folder=False)


def run(args) -> int:
    config = load_config(args)
    check_outputs(args)
    dataset = open_dataset(args.dataset, calib_path=args.calib)
    result, evaluation = perform_run(dataset, config, args.out, args.rerun, args.spawn, args.delta,
                                     args.max_frames, progress=not args.quiet, formats=(args.format,),
                                     config_label=config_name(args), notify=cli_notifier("run"),
                                     concurrent=not args.sequential)
    for line in summary_lines(result, evaluation, args.delta):
        print(line)
    if dataset.undistortion is not None:
        print(dataset.undistortion.describe())
    print(f"outputs: {args.out} (report: {args.out / 'report.md'})")
    if result.interrupted:
        print("interrupted: the outputs hold the frames processed so far", file=sys.stderr)
        return 130
    return 0
