"""``granite-sim``: render Mars test-bench flights with exact ground truth.

    granite-sim render SCENARIO --out DIR [--width W --height H --samples N --frames A:B
                                           --grayscale|--color --depth-format npy|inv16
                                           --no-sensor --quiet]
    granite-sim list
    granite-sim view DATASET [--rerun FILE.rrd | --spawn] [--no-depth]

SCENARIO is a bundled scenario name (``granite-sim list``) or a path to a ``.toml`` file.
Runs are resumable: running the same command again skips finished frames. Bad input (unknown
key, value out of range, flight below ground, unwritable output) is reported as one line
with exit status 2 before anything is rendered.
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from collections.abc import Sequence

from granite.cli.main import OneLineErrorParser
from granite.errors import GraniteError
from simulation.scenario import SCENARIO_DIR, load_scenario, with_overrides


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(
        prog="granite-sim",
        description="Blender Mars test-bench: reproducible flights with exact ground truth.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    r = sub.add_parser("render", help="render a scenario into an EuRoC/ASL folder")
    r.add_argument("scenario", help="bundled scenario name or path to a .toml file")
    r.add_argument("--out", required=True, help="output folder (created; resumable)")
    r.add_argument("--width", type=_positive_int, help="image width (intrinsics rescaled)")
    r.add_argument("--height", type=_positive_int, help="image height (intrinsics rescaled)")
    r.add_argument("--samples", type=_positive_int, help="Cycles samples per pixel")
    r.add_argument("--frames", metavar="A:B", help="render frames A..B-1 only")
    colour = r.add_mutually_exclusive_group()
    colour.add_argument("--grayscale", dest="grayscale", action="store_true", default=None,
                        help="monochrome images (the default: the sensor model is a monochrome "
                        "navigation camera)")
    colour.add_argument("--color", dest="grayscale", action="store_false",
                        help="colour images: the sensor model applied per channel (a colour "
                        "sensor without a Bayer mosaic); readers convert them to grayscale, "
                        "which averages the channels' noise")
    r.add_argument("--depth-format", choices=("npy", "inv16"),
                   help="float32 .npy (exact) or inv16: 16-bit PNG of inverse depth (compact)")
    r.add_argument("--no-sensor", action="store_true",
                   help="ideal camera: the scenario's exposure and encoding without the sensor "
                   "model (no noise, fixed pattern, blur, vignetting or JPEG), for comparisons")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    sub.add_parser("list", help="list the bundled scenarios")
    v = sub.add_parser(
        "view", help="make a rerun recording of a rendered dataset",
        description="Log a rendered dataset to rerun: images, depth maps, the ground-truth "
        "trajectory and the camera frustum per frame (entity layout: README).")
    v.add_argument("dataset", help="dataset folder (output of granite-sim render)")
    target = v.add_mutually_exclusive_group()
    target.add_argument("--rerun", metavar="FILE.rrd", help="recording to write "
                        "(default: DATASET/dataset.rrd)")
    target.add_argument("--spawn", action="store_true", help="stream to a new rerun viewer")
    v.add_argument("--no-depth", action="store_true", help="leave the depth maps out")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def cmd_list() -> int:
    rows = []
    for path in sorted(SCENARIO_DIR.glob("*.toml")):
        try:
            s = load_scenario(path)
            line = (f"{s.name:<12} {s.flight.type:<10} {s.n_frames:>5} frames "
                    f"{s.camera.width}x{s.camera.height}  {s.description}")
        except (GraniteError, tomllib.TOMLDecodeError) as error:
            line = f"{path.stem:<12} INVALID: {error}"
        rows.append(line)
    print("\n".join(rows) if rows else f"no scenarios in {SCENARIO_DIR}")
    return 0


def cmd_render(args: argparse.Namespace, argv: list[str]) -> int:
    from simulation.run import prepare, render_run

    scenario = with_overrides(load_scenario(args.scenario), width=args.width,
                              height=args.height, samples=args.samples,
                              grayscale=args.grayscale, depth_format=args.depth_format,
                              sensor=False if args.no_sensor else None)
    plan, writer, frames = prepare(scenario, args.out, args.frames,
                                   command=["granite-sim", *argv])

    def progress(items, total):
        from tqdm import tqdm

        return tqdm(items, total=total, unit="frame", desc=scenario.name,
                    disable=args.quiet, dynamic_ncols=True)

    summary = render_run(plan, writer, frames, progress)
    n, wall = summary["rendered"], summary.get("wall_seconds")
    mean = f", {wall / n:.2f} s/frame" if n and wall else ""
    if n > 1 and wall:  # the first frame also builds Cycles' BVH
        first = summary["first_render_seconds"]
        mean += f" ({(wall - first) / (n - 1):.2f} after the first, which took {first:.1f} s)"
    print(f"{scenario.name}: rendered {summary['rendered']} frames, skipped "
          f"{summary['skipped']} finished ones{mean} -> {args.out}", file=sys.stderr)
    return 130 if summary.get("interrupted") else 0


def cmd_view(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from granite.io import open_dataset
    from granite.visualization.dataset_view import log_dataset
    from granite.visualization.rerun_logger import recording_path
    from simulation.depth import depth_reader

    dataset = open_dataset(args.dataset)
    rrd = recording_path(args.rerun, args.spawn, Path(args.dataset) / "dataset.rrd")
    depth_of = None if args.no_depth else depth_reader(dataset)
    counts = log_dataset(
        dataset, rrd, args.spawn, depth_of,
        progress=lambda frames: tqdm(frames, total=len(dataset), unit="frame", desc=dataset.name,
                                     disable=args.quiet, dynamic_ncols=True),
        warn=lambda text: tqdm.write(f"granite-sim view: warning: {text}", file=sys.stderr))
    where = f"recording: {rrd}" if rrd else "streamed to the viewer"
    print(f"{dataset.name}: {counts['frames']} frames, {counts['images']} images, "
          f"{counts['poses']} ground-truth poses, {counts['depth_maps']} depth maps; {where}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    try:
        if args.command == "list":
            return cmd_list()
        if args.command == "view":
            return cmd_view(args)
        return cmd_render(args, argv)
    except GraniteError as error:
        print(f"granite-sim {args.command}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        kept = ("no recording written" if args.command == "view" else
                "finished frames are kept; run the same command again to resume")
        print(f"granite-sim {args.command}: interrupted ({kept})", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
