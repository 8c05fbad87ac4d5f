"""``granite demo``: the main job. Render a Mars scenario with the test-bench, run the VO on it,
evaluate against the exact ground truth, and write plots, a report and a rerun recording."""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
from pathlib import Path

from granite.cli.eval_cmd import positive_seconds
from granite.cli.run_cmd import cli_notifier, config_name, perform_run, positive_int, summary_lines, write_run_report
from granite.errors import GraniteError, InputError
from granite.estimator.config import VoConfig
from granite.evaluation import DEFAULT_RPE_DELTA
from granite.io import atomic_write_text, check_writable, open_dataset

DESCRIPTION = f"""\
The main job, in one command:

  1. granite-sim render SCENARIO --out OUT/dataset   (resumable: finished frames are kept)
  2. granite run OUT/dataset --out OUT/run --rerun OUT/recording.rrd
  3. evaluation against the rendered ground truth -> OUT/run/evaluation.json
     (RPE Δ = {DEFAULT_RPE_DELTA:g} s unless --delta says otherwise)
  4. plots OUT/run/*.png and the report OUT/report.md (also OUT/run/report.md)

The scenario, the overrides, the configuration and the output folder are checked before
anything is rendered (bad input: one error line, exit status 2). Ctrl-C keeps what is finished
(rendered frames; the frames the VO processed, with their outputs) and exits with 130; the
same command resumes the rendering. Open the recording with `rerun OUT/recording.rrd`.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="render the default Mars scenario, run, evaluate, report",
        description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (default: runs/demo)")
    p.add_argument("--scenario", default="default", help="scenario name or TOML file (default: default)")
    p.add_argument("--width", type=positive_int, help="override the scenario's image width")
    p.add_argument("--height", type=positive_int, help="override the scenario's image height")
    p.add_argument("--samples", type=positive_int, help="override the scenario's Cycles samples")
    p.add_argument("--config", type=Path, help="VO configuration (TOML; default: the built-in defaults, "
                   "configs/reference.toml = the reference's)")
    p.add_argument("--delta", type=positive_seconds, default=DEFAULT_RPE_DELTA, metavar="SECONDS",
                   help=f"RPE delta in seconds (default: {DEFAULT_RPE_DELTA:g}, as in every granite command)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def check_scenario(args) -> None:
    """The scenario file and the overrides, checked as granite-sim will (ConfigError)."""
    from simulation.scenario import load_scenario, with_overrides

    with_overrides(load_scenario(args.scenario), width=args.width, height=args.height, samples=args.samples)


def render(args, dataset_dir: Path) -> int:
    """Run granite-sim; returns its exit status. Ctrl-C lets it finish its files (it got the
    same signal, or is sent one) and raises KeyboardInterrupt."""
    cmd = [sys.executable, "-m", "simulation.cli", "render", str(args.scenario), "--out", str(dataset_dir)]
    for flag in ("width", "height", "samples"):
        value = getattr(args, flag)
        if value is not None:
            cmd += [f"--{flag}", str(value)]
    if args.quiet:
        cmd.append("--quiet")
    print("render:", " ".join(cmd[2:]), flush=True)
    proc = subprocess.Popen(cmd)
    try:
        code = proc.wait()
    except KeyboardInterrupt:
        try:
            try:
                proc.wait(timeout=2.0)
            except subprocess.TimeoutExpired:  # the signal reached this process only
                proc.send_signal(signal.SIGINT)
                proc.wait(timeout=30.0)
        except (KeyboardInterrupt, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait()
        raise
    if code in (130, -signal.SIGINT):
        raise KeyboardInterrupt
    return code


def run(args) -> int:
    config = VoConfig.load(args.config) if args.config else VoConfig()
    check_scenario(args)
    check_writable(args.out)
    dataset_dir = args.out / "dataset"
    try:
        code = render(args, dataset_dir)
    except KeyboardInterrupt:
        print(f"granite demo: interrupted while rendering; the finished frames are kept in {dataset_dir} "
              "(the same command resumes)", file=sys.stderr)
        return 130
    if code == 2:
        return 2  # granite-sim printed the one error line
    if code != 0:
        raise GraniteError(f"rendering the scenario failed (granite-sim exit code {code})")
    dataset = open_dataset(dataset_dir)
    if dataset.ground_truth is None:
        raise InputError("the rendered dataset has no ground truth", dataset_dir)
    run_dir = args.out / "run"
    label = config_name(args)
    result, evaluation = perform_run(
        dataset, config, run_dir, args.out / "recording.rrd", False, args.delta,
        progress=not args.quiet, config_label=label, report=False, notify=cli_notifier("demo"),
    )
    header = (f"scenario: `{args.scenario}`", f"rerun recording: `{args.out / 'recording.rrd'}`")
    write_run_report(run_dir, result, dataset, evaluation, args.delta, label,
                     title=f"granite-py demo: {args.scenario}", header=header,
                     copies=((args.out / "report.md", "run/"),))
    (args.out / "evaluation.json").unlink(missing_ok=True)
    if evaluation is not None:
        atomic_write_text(args.out / "evaluation.json", json.dumps(evaluation, indent=2, allow_nan=False) + "\n")
    for line in summary_lines(result, evaluation, args.delta):
        print(line)
    print(f"report: {args.out / 'report.md'}\nrecording: {args.out / 'recording.rrd'} "
          f"(open with: rerun {args.out / 'recording.rrd'})")
    if result.interrupted:
        print("granite demo: interrupted: the outputs hold the frames processed so far", file=sys.stderr)
        return 130
    return 0
