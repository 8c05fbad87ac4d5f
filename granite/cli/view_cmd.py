"""``granite view``: a rerun recording of a finished run, without re-running the VO."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from granite.errors import InputError
from granite.estimator.diagnostics import read_diagnostics
from granite.estimator.records import read_records
from granite.io import open_dataset, read_estimate


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "view", help="make a rerun recording of a finished run folder",
        description="Build a rerun recording from a run folder written by `granite run` (images are "
        "read from the dataset recorded in summary.json, or --dataset). Entity layout: README.",
    )
    p.add_argument("run_dir", type=Path, help="run folder (output of granite run)")
    p.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="recording to write (default: RUN_DIR/recording.rrd)")
    p.add_argument("--spawn", action="store_true", help="stream to a rerun viewer instead of a file")
    p.add_argument("--dataset", type=Path, help="dataset folder (default: the one in summary.json; "
                   "a relative one is looked for in the current folder, then beside RUN_DIR)")
    return p


def recorded_dataset(summary: object, summary_path: Path) -> Path:
    """The dataset folder recorded in a run's summary.json. A relative path is looked for in
    the current folder (where ``granite run`` was typically started), then beside the run
    folder; the error names the file it came from and every place looked in."""
    if not isinstance(summary, dict):
        raise InputError("top level must be a JSON object", summary_path)
    stored = summary.get("dataset")
    if not isinstance(stored, str) or not stored:
        raise InputError(f"\"dataset\" must be a folder path (a string), got {stored!r}; pass --dataset DIR",
                         summary_path)
    candidates = [Path(stored)]
    beside_run = summary_path.parent.parent / stored
    if not candidates[0].is_absolute() and beside_run.absolute() != candidates[0].absolute():
        candidates.append(beside_run)
    found = next((c for c in candidates if c.exists()), None)
    if found is None:
        looked = " or ".join(str(c.absolute()) for c in candidates)
        raise InputError(f"dataset folder {stored!r} recorded in this file not found (looked for {looked}); "
                         "pass --dataset DIR", summary_path)
    return found


def run(args) -> int:
    run_dir = args.run_dir
    if not run_dir.is_dir():
        raise InputError("run folder not found", run_dir)
    summary_path = run_dir / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
    except FileNotFoundError:
        raise InputError("summary.json not found: not a granite run folder", run_dir) from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read ({error})", summary_path) from None
    except json.JSONDecodeError as error:
        raise InputError(f"malformed JSON ({error})", summary_path) from None
    dataset = open_dataset(args.dataset or recorded_dataset(summary, summary_path))
    trajectory, _ = read_estimate(run_dir)  # with the sub-maps of submaps.csv (or the 9th column)
    diagnostics = read_diagnostics(run_dir / "diagnostics.csv")
    records = read_records(run_dir / "landmarks.npz")
    # Skipped frames have a diagnostics row and a record but no pose (older runs: a pose too).
    posed = [d for d in diagnostics if d.state != "skipped"]
    if len(records) != len(diagnostics) or len(trajectory) not in (len(posed), len(diagnostics)):
        raise InputError("trajectory, diagnostics and records disagree on the number of frames", run_dir)
    # rerun is imported here, not with the module: every granite command parses its arguments
    # through this module, and importing rerun costs ~44 MB (docs/architecture.md, "Memory")
    from granite.visualization.rerun_logger import recording_path
    from granite.visualization.run_view import RunView

    rrd = recording_path(args.rerun, args.spawn, run_dir / "recording.rrd")
    view = RunView(f"granite-view-{dataset.name}", dataset.calibration, dataset.ground_truth, rrd, args.spawn)
    try:
        for record, diag in zip(records, diagnostics):
            frame = dataset.frame(record.index)
            view.log_frame(record, frame.image, diag, frame.path)
        view.finish(trajectory)
    except BaseException:
        view.discard()
        raise
    print(f"recording: {rrd}" if rrd else "streamed to the viewer")
    return 0
