"""``granite demo``: the main job. Render a Mars scenario with the test-bench, run the VO on it,
evaluate against the exact ground truth, and write a report and a rerun recording."""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
from pathlib import Path

from granite.errors import GraniteError, InputError
from granite.estimator.config import VoConfig
from granite.io import atomic_write_text, open_dataset
from granite.cli.run_cmd import perform_run, summary_lines

DESCRIPTION = """\
The main job, in one command:

  1. granite-sim render SCENARIO --out OUT/dataset   (resumable: finished frames are kept)
  2. granite run OUT/dataset --out OUT/run --rerun OUT/recording.rrd
  3. evaluation against the rendered ground truth -> OUT/run/evaluation.json
  4. OUT/report.md: scenario, run and evaluation summary

Open the recording with `rerun OUT/recording.rrd`.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="render the default Mars scenario, run, evaluate, report",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (default: runs/demo)")
    p.add_argument("--scenario", default="default", help="scenario name or TOML file (default: default)")
    p.add_argument("--width", type=int, help="override the scenario's image width")
    p.add_argument("--height", type=int, help="override the scenario's image height")
    p.add_argument("--samples", type=int, help="override the scenario's Cycles samples")
    p.add_argument("--config", type=Path, help="VO configuration (TOML)")
    p.add_argument("--delta", type=float, default=1.0, help="RPE delta in seconds (default: 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def render(args, dataset_dir: Path) -> None:
    cmd = [sys.executable, "-m", "simulation.cli", "render", str(args.scenario), "--out", str(dataset_dir)]
    for flag in ("width", "height", "samples"):
        value = getattr(args, flag)
        if value is not None:
            cmd += [f"--{flag}", str(value)]
    if args.quiet:
        cmd.append("--quiet")
    print("render:", " ".join(cmd[2:]), flush=True)
    completed = subprocess.run(cmd)
    if completed.returncode != 0:
        raise GraniteError(f"rendering the scenario failed (granite-sim exit code {completed.returncode})")


def write_report(path: Path, args, dataset, result, evaluation) -> None:
    lines = [
        "# granite-py demo report",
        "",
        f"- date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}",
        f"- scenario: `{args.scenario}`; dataset `{dataset.root}` ({len(dataset)} images, format {dataset.format})",
        f"- run folder: `{args.out / 'run'}`; rerun recording: `{args.out / 'recording.rrd'}`",
        "",
        "## Result",
        "",
        *[f"- {line}" for line in summary_lines(result, evaluation, args.delta)],
        "",
    ]
    if evaluation is not None:
        lines += ["## Evaluation", "", "| metric | value |", "| --- | --- |"]
        for key in ("ate_rmse", "ate_over_path_length", "rpe_rmse", "tracking_percentage", "restarts",
                    "path_length", "num_poses", "num_rpe_pairs"):
            value = evaluation.get(key)
            lines.append(f"| {key} | {value:.6g} |" if isinstance(value, float) else f"| {key} | {value} |")
        lines += ["", f"ATE after Sim(3) alignment per sub-map; RPE as the paper's Eq. 18-20 with Δ = {args.delta:g} s."]
    atomic_write_text(path, "\n".join(lines) + "\n")


def run(args) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    dataset_dir = args.out / "dataset"
    render(args, dataset_dir)
    dataset = open_dataset(dataset_dir)
    if dataset.ground_truth is None:
        raise InputError("the rendered dataset has no ground truth", dataset_dir)
    config = VoConfig.load(args.config) if args.config else VoConfig()
    result, evaluation = perform_run(
        dataset, config, args.out / "run", args.out / "recording.rrd", False, args.delta,
        progress=not args.quiet,
    )
    write_report(args.out / "report.md", args, dataset, result, evaluation)
    atomic_write_text(args.out / "evaluation.json", json.dumps(evaluation, indent=2) + "\n")
    for line in summary_lines(result, evaluation, args.delta):
        print(line)
    print(f"report: {args.out / 'report.md'}\nrecording: {args.out / 'recording.rrd'} (open with: rerun {args.out / 'recording.rrd'})")
    return 0
