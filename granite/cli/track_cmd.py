"""``granite track``: run the optical-flow frontend alone over a dataset and save the tracks."""

from __future__ import annotations

import argparse
import io
import json
import sys
import tomllib
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from granite.cli.eval_cmd import int_at_least
from granite.errors import ConfigError, InputError

DESCRIPTION = """\
Run the optical-flow frontend (multi-level FAST detection + KLT patch tracking, paper
Sec. IV-A) over every frame of DATASET and write all tracks to FILE: one row per track and
frame. Positions are level-0 pixels, the centre of the top-left pixel being (0, 0).
Unusable frames (unreadable, wrong size or type, blank) are reported and have no rows; the
frame after them is tracked from the last good one."""

EPILOG = """\
output (chosen by the extension of --out):
  .csv  header 'timestamp,id,x,y,level'; timestamp in seconds (9 decimals), id the
        persistent track id, x y the patch centre (pixels), level the pyramid level the
        track was created on (its observation weight is 1/2^level, paper Eq. 7).
  .npz  arrays timestamp, id, x, y, level (one entry per row as in the CSV), plus
        frame_timestamp, frame_tracks, frame_rejected (one entry per frame),
        frame_ms (frames x 3: pyramid, detection, tracking) and config (JSON string).

config (--config FILE.toml): keys of OpticalFlowConfig at the top level or in an
[optical_flow] table, e.g. levels = 6, grid_size = 40, detect_all_levels = false.

examples:
  granite track assets/sequences/hover --out tracks.csv
  granite track MH_01_easy --out tracks.npz --finest-level-only"""

_FORMATS = (".csv", ".npz")


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    parser = subparsers.add_parser(
        "track",
        help="run the optical-flow frontend alone and save every frame's tracks",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("dataset", type=Path, metavar="DATASET",
                        help="dataset folder (EuRoC/ASL, test-bench, TUM RGB-D, KITTI)")
    parser.add_argument("--out", required=True, type=Path, metavar="FILE",
                        help="output file, .csv or .npz (written atomically)")
    parser.add_argument("--calib", type=Path, metavar="CALIB",
                        help="Basalt calib.json; its resolution is the expected image size")
    parser.add_argument("--config", type=Path, metavar="TOML",
                        help="optical-flow settings (see below)")
    parser.add_argument("--levels", type=int, metavar="N", help="pyramid levels (default 6)")
    parser.add_argument("--grid-size", type=int, metavar="PX",
                        help="detection cell size in pixels (default 40)")
    parser.add_argument("--finest-level-only", action="store_true",
                        help="detect corners on level 0 only (the paper's ablation †)")
    parser.add_argument("--start", type=int_at_least(0), default=0, metavar="I", help="first frame index")
    parser.add_argument("--stop", type=int_at_least(1), metavar="I", help="stop before this frame index")
    parser.add_argument("--quiet", action="store_true", help="no progress bar and summary")
    return parser


def load_config(args: argparse.Namespace):
    """The OpticalFlowConfig from --config (a VO configuration, or a bare [optical_flow] table)
    and the command-line overrides, checked by the VO configuration's validator."""
    from granite.estimator.config import VoConfig

    data: dict[str, Any] = {}
    if args.config is not None:
        try:
            data = tomllib.loads(args.config.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError("config file not found", args.config) from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
            raise InputError(f"cannot read config: {error}", args.config) from None
        if not any(isinstance(v, dict) for v in data.values()):
            data = {"optical_flow": data}  # a bare table of optical-flow keys
        try:
            VoConfig.from_dict(data)
        except ConfigError as error:
            raise ConfigError(f"{args.config}: {error}") from None
    values = dict(data.get("optical_flow", {}))
    overrides = {"levels": args.levels, "grid_size": args.grid_size,
                 "detect_all_levels": False if args.finest_level_only else None}
    values.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return VoConfig.from_dict({"optical_flow": values}).optical_flow
    except ConfigError as error:
        raise ConfigError(f"command line: {error}") from None


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from granite._numba_cache import compile_notice
    from granite.io import check_writable, open_dataset
    from granite.optical_flow import FrameRejectedWarning, FrameToFrameOpticalFlow, tracking

    suffix = args.out.suffix.lower()
    if suffix not in _FORMATS:
        raise InputError(f"unknown output format {args.out.suffix!r}; use .csv or .npz", args.out)
    if args.stop is not None and args.start >= args.stop:
        raise InputError(f"--start {args.start} must be less than --stop {args.stop}")
    config = load_config(args)
    check_writable(args.out, folder=False)
    dataset = open_dataset(args.dataset, calib_path=args.calib)
    if args.start >= len(dataset):
        raise InputError(f"--start {args.start} is past the last frame (the dataset has {len(dataset)} frames, "
                         f"0..{len(dataset) - 1})", dataset.root)
    size = None
    if dataset.calibration is not None:
        size = (dataset.calibration.width, dataset.calibration.height)
    flow = FrameToFrameOpticalFlow(config, image_size=size)

    rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
    frame_t, frame_n, frame_rejected, frame_ms = [], [], [], []
    frames = dataset.frames(args.start, args.stop)
    total = min(len(dataset), args.stop if args.stop is not None else len(dataset)) - args.start
    bar = tqdm(frames, total=total, unit="frame", disable=args.quiet, file=sys.stderr,
               desc=f"track {dataset.name}")
    if not args.quiet and (notice := compile_notice(
            "granite track", (tracking._track_passes_claimed, tracking._track_passes))):
        bar.write(notice, file=sys.stderr)
    for frame in bar:
        if frame.image is None:
            _warn(bar, f"frame {frame.index} (t={frame.timestamp:.6f}): {frame.error}; no tracks")
            result = None
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", FrameRejectedWarning)  # reported below
                result = flow.process(frame.timestamp, frame.image)
            if result.rejected:
                _warn(bar, f"frame {frame.index} (t={frame.timestamp:.6f}): {result.rejected}; no tracks")
        frame_t.append(frame.timestamp)
        if result is None or result.rejected:
            frame_n.append(0)
            frame_rejected.append(True)
            frame_ms.append((0.0, 0.0, 0.0))
            continue
        frame_n.append(len(result))
        frame_rejected.append(False)
        frame_ms.append(tuple(result.timing[k] for k in ("pyramid", "detection", "tracking")))
        rows.append((result.timestamp, result.ids, result.positions, result.levels))
        bar.set_postfix(tracks=len(result), refresh=False)
    bar.close()

    frames_info = {
        "frame_timestamp": np.asarray(frame_t, dtype=np.float64),
        "frame_tracks": np.asarray(frame_n, dtype=np.int64),
        "frame_rejected": np.asarray(frame_rejected, dtype=bool),
        "frame_ms": np.asarray(frame_ms, dtype=np.float64).reshape(-1, 3),
    }
    write_tracks(args.out, rows, frames_info, config.to_dict())
    if not args.quiet:
        ok = ~frames_info["frame_rejected"]
        n_ok = int(ok.sum())
        med = np.median(frames_info["frame_ms"][ok], axis=0) if n_ok else np.zeros(3)
        tracks = float(np.mean(frames_info["frame_tracks"][ok])) if n_ok else 0.0
        print(
            f"{len(frame_t)} frames ({len(frame_t) - n_ok} rejected), {tracks:.1f} tracks/frame, "
            f"{flow.next_id} track ids; median ms/frame: pyramid {med[0]:.2f}, "
            f"detection {med[1]:.2f}, tracking {med[2]:.2f}; wrote {args.out}"
        )
    return 0


def _warn(bar: Any, message: str) -> None:
    bar.write(f"granite track: warning: {message}", file=sys.stderr)


def write_tracks(
    path: Path,
    rows: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]],
    frames: dict[str, np.ndarray],
    config: dict[str, Any],
) -> None:
    """Write the tracks as CSV or NPZ (by extension), atomically."""
    from granite.io import atomic_path, atomic_write_text

    counts = [len(ids) for _, ids, _, _ in rows]
    t = np.repeat(np.array([r[0] for r in rows], dtype=np.float64), counts)
    ids = np.concatenate([r[1] for r in rows]) if rows else np.zeros(0, np.int64)
    pos = np.concatenate([r[2] for r in rows]) if rows else np.zeros((0, 2))
    lvl = np.concatenate([r[3] for r in rows]) if rows else np.zeros(0, np.int64)
    if path.suffix.lower() == ".npz":
        with atomic_path(path) as tmp:
            np.savez_compressed(
                tmp, timestamp=t, id=ids.astype(np.int64), x=pos[:, 0], y=pos[:, 1],
                level=lvl.astype(np.int64), config=np.array(json.dumps(config)), **frames,
            )
        return
    buf = io.StringIO()
    buf.write("timestamp,id,x,y,level\n")
    if len(t):
        table = np.empty(len(t), dtype=[("t", "f8"), ("id", "i8"), ("x", "f8"), ("y", "f8"), ("l", "i8")])
        table["t"], table["id"], table["x"], table["y"], table["l"] = t, ids, pos[:, 0], pos[:, 1], lvl
        np.savetxt(buf, table, fmt=("%.9f", "%d", "%.4f", "%.4f", "%d"), delimiter=",")
    atomic_write_text(path, buf.getvalue())
