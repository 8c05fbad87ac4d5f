"""Whole-pipeline benchmark: the VO on every test-bench scenario, as the paper's Tables I and II.

    python benchmarks/bench_vo.py [--data DIR] [--scenarios spiral rotation ...] [--ablations]
                                  [--width 640 --height 480] [--delta 1] [--no-render] [--rerun]
                                  [--config FILE ...] [--datasets DIR ...]

Renders each scenario at WIDTHxHEIGHT into DIR/<scenario> with granite-sim when it is not there
yet (resumable), runs `granite run` on it and prints one row per scenario (and per ablation:
† corners on the finest level only, ‡ the current frame made keyframe): restarts, tracking
percentage, RMS RPE (paper Eq. 18-20, Δ = --delta s; 1 s suits our 20 Hz ground truth: 20
pose pairs per second of flight and 1-6 m of motion), Sim(3) ATE as a fraction of the path
length, and frames per second of the VO alone (rendering, image decoding and logging excluded).
With --rerun each scenario's "ours" run is repeated with a rerun recording, and the logging
cost (wall time spent in the recording's per-frame logging and final 3D content, per frame;
the one-time start-up, which builds the blueprint, apart) is printed beside the VO's frame
time. Results also go to DIR/bench_vo.json.

Configurations: the built-in defaults ("ours": configs/mono_default.toml, our additions on) unless
--config names files (repeatable; configs/reference.toml = the reference configuration, rows
"reference", "reference †", ...). Every row says which configuration it comes from.
--datasets runs on existing dataset folders instead of rendering (e.g. assets/sequences/*).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run` (same numbers)

import numpy as np  # noqa: E402

from granite.estimator.config import VoConfig  # noqa: E402
from granite.cli.run_cmd import perform_run  # noqa: E402
from granite.evaluation import DEFAULT_RPE_DELTA  # noqa: E402
from granite.io import open_dataset  # noqa: E402

SCENARIOS = ("spiral", "rotation", "hover", "survey", "framedrop", "aggressive")
#: Frame windows rendered by default (20 Hz), chosen to hold each scenario's characteristic
#: motion while keeping the rendering time of the whole table near 45 min on 2 cores; --full
#: renders complete flights (about 4300 frames, 2-3 h).
WINDOWS = {"spiral": "0:300", "rotation": "40:280", "hover": "0:160", "survey": "0:200",
           "framedrop": "0:200", "aggressive": "0:160"}
VARIANTS = {"": {}, " †": {"optical_flow": {"detect_all_levels": False}},
            " ‡": {"estimator": {"previous_frame_as_keyframe": False}}}


def with_overrides(config: VoConfig, overrides: dict) -> VoConfig:
    """``config`` with ``{table: {key: value}}`` replaced (validated)."""
    import dataclasses

    tables = {name: dataclasses.replace(getattr(config, name), **values) for name, values in overrides.items()}
    return dataclasses.replace(config, **tables)


def ensure_rendered(scenario: str, folder: Path, width: int, height: int, frames: str | None) -> None:
    cmd = [sys.executable, "-m", "simulation.cli", "render", scenario, "--out", str(folder),
           "--width", str(width), "--height", str(height), "--grayscale"]
    if frames:
        cmd += ["--frames", frames]
    if subprocess.run(cmd).returncode != 0:
        raise SystemExit(f"rendering {scenario} failed")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("runs/bench"))
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--ablations", action="store_true", help="also run † and ‡")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--delta", type=float, default=DEFAULT_RPE_DELTA)
    parser.add_argument("--config", type=Path, action="append",
                        help="configuration file (repeatable; default: the built-in defaults)")
    parser.add_argument("--datasets", type=Path, nargs="+",
                        help="run on these dataset folders instead of rendering the scenarios")
    parser.add_argument("--no-render", action="store_true", help="use only already rendered datasets")
    parser.add_argument("--full", action="store_true", help="render and run complete flights, not the windows")
    parser.add_argument("--rerun", action="store_true",
                        help="repeat 'ours' with a rerun recording and print the logging cost")
    args = parser.parse_args()

    rows = []
    logging_cost: list[dict] = []
    variants = VARIANTS if args.ablations else {"": {}}
    configs = {"ours": (VoConfig(), "built-in defaults (configs/mono_default.toml)")}
    if args.config:
        configs = {("ours" if p.stem == "mono_default" else p.stem): (VoConfig.load(p), str(p)) for p in args.config}
    for name, (_, label) in configs.items():
        print(f"configuration {name}: {label}")
    if args.datasets:
        folders = [(p.name, p, None) for p in args.datasets]
    else:
        folders = []
        for scenario in args.scenarios:
            window = None if args.full else WINDOWS.get(scenario)
            suffix = "" if window is None else "_" + window.replace(":", "-")
            folders.append((scenario, args.data / f"{scenario}_{args.width}x{args.height}{suffix}", window))
    for scenario, folder, window in folders:
        if not args.datasets and not args.no_render:
            ensure_rendered(scenario, folder, args.width, args.height, window)
        if not (folder / "mav0").is_dir():
            print(f"{scenario}: not rendered, skipped")
            continue
        dataset = open_dataset(folder)
        for (base, (base_config, config_label)), (suffix_name, overrides) in (
                (c, v) for c in configs.items() for v in variants.items()):
            name = base + suffix_name
            config = with_overrides(base_config, overrides)
            out = args.data / "runs" / f"{scenario}_{name.replace(' ', '_')}"
            t0 = time.perf_counter()
            result, ev = perform_run(dataset, config, out, None, delta=args.delta, progress=False,
                                     config_label=config_label + suffix_name)
            wall = time.perf_counter() - t0
            if ev is None:
                print(f"{scenario:<11} {name:<12} evaluation failed: {result.evaluation_error}", flush=True)
                continue
            if args.rerun and name == "ours":  # the built-in defaults, no ablation
                logged, _ = perform_run(dataset, config, out, out / "recording.rrd", delta=args.delta,
                                        progress=False)
                n = len(logged.diagnostics)
                vo_ms = float(np.mean([d.processing_ms for d in logged.diagnostics]))
                log_ms = 1e3 * logged.logging_seconds / n
                logging_cost.append({"scenario": scenario, "vo_ms_per_frame": vo_ms,
                                     "logging_ms_per_frame": log_ms,
                                     "startup_s": logged.logging_startup_seconds,
                                     "recording_mb": (out / "recording.rrd").stat().st_size / 1e6})
                print(f"{scenario:<11} logging {log_ms:.1f} ms/frame = {100 * log_ms / vo_ms:.0f} % "
                      f"of the VO's {vo_ms:.1f} ms/frame (+{logged.logging_startup_seconds:.1f} s once)",
                      flush=True)
            ms = np.array([d.processing_ms for d in result.diagnostics])
            rows.append({
                "scenario": scenario, "frames_window": window or "all", "variant": name,
                "configuration": config_label + suffix_name, "frames": len(result.diagnostics),
                "restarts": ev["restarts"], "tracking_percentage": ev["tracking_percentage"],
                "rpe_rmse": ev["rpe_rmse"], "ate_over_path_length": ev["ate_over_path_length"],
                "path_length": ev["path_length"], "vo_fps": 1000.0 / ms.mean(), "wall_s": wall,
            })
            r = rows[-1]
            print(f"{scenario:<11} {name:<12} restarts {r['restarts']:>2}  tracking {r['tracking_percentage']:6.1f} %  "
                  f"RPE {r['rpe_rmse'] if r['rpe_rmse'] is not None else float('nan'):.3f} m  "
                  f"ATE {100 * (r['ate_over_path_length'] or float('nan')):.2f} % of {r['path_length']:.0f} m  "
                  f"{r['vo_fps']:.1f} fps", flush=True)

    print(f"\n| scenario (frames) | variant | restarts | tracking % | RMS RPE (Δ={args.delta:g} s) [m] | ATE / path | VO fps |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        rpe = "n/a" if r["rpe_rmse"] is None else f"{r['rpe_rmse']:.3f}"
        ate = "n/a" if r["ate_over_path_length"] is None else f"{100 * r['ate_over_path_length']:.2f} %"
        print(f"| {r['scenario']} ({r['frames_window']}) | {r['variant']} | {r['restarts']} | {r['tracking_percentage']:.1f} | {rpe} | {ate} | {r['vo_fps']:.1f} |")
    for c in logging_cost:
        print(f"logging cost {c['scenario']}: {c['logging_ms_per_frame']:.1f} ms/frame, "
              f"{100 * c['logging_ms_per_frame'] / c['vo_ms_per_frame']:.0f} % of the VO's frame time, "
              f"start-up {c['startup_s']:.1f} s, recording {c['recording_mb']:.0f} MB")
    args.data.mkdir(parents=True, exist_ok=True)
    report = {"rows": rows, "logging_cost": logging_cost, "delta": args.delta,
              "configurations": {name: label for name, (_, label) in configs.items()}}
    (args.data / "bench_vo.json").write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
