"""Whole-pipeline benchmark: the VO on every test-bench scenario, as the paper's Tables I and II.
A thin wrapper of ``granite bench`` (granite.bench): its options become a study, which runs on a
Dask LocalCluster (or --scheduler, or --serial) and writes DIR/results.csv, DIR/report.md, the
plots and every run folder (docs/bench.md); the table is printed as before.

    python benchmarks/bench_vo.py [--data DIR] [--scenarios spiral rotation ...] [--ablations]
                                  [--width 640 --height 480] [--delta 1] [--no-render] [--rerun]
                                  [--config FILE ...] [--datasets DIR ...] [--full]
                                  [--workers N | --scheduler ADDRESS | --serial]

Renders each scenario at WIDTHxHEIGHT (its frame window, see WINDOWS; --full: the whole flight)
into DIR/sequences/ with granite-sim when it is not there yet (resumable), runs the VO on it and
prints one row per scenario and configuration (and per ablation: † corners on the finest level
only, ‡ the current frame made keyframe): restarts, tracking percentage, RMS RPE (paper Eq.
18-20, Δ = --delta s; 1 s suits our 20 Hz ground truth), Sim(3) ATE as a fraction of the path
length, and frames per second of the VO alone (median frame time). With --rerun each scenario's
"ours" run is repeated with a rerun recording, and the logging cost per frame is printed beside
the VO's frame time. Results also go to DIR/bench_vo.json.

Configurations: the built-in defaults ("ours": configs/mono_default.toml, our additions on) unless
--config names files (repeatable; configs/reference.toml = the reference configuration, rows
"reference", "reference †", ...). --datasets runs on existing dataset folders instead of
rendering (e.g. assets/sequences/*). The same as a study file: studies/paper_tables.toml.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run` (same numbers)

import numpy as np  # noqa: E402

from granite.bench.study import parse_study  # noqa: E402
from granite.bench.tasks import complete_marker, run_dir  # noqa: E402
from granite.cli.bench_cmd import execute  # noqa: E402
from granite.evaluation import DEFAULT_RPE_DELTA  # noqa: E402

SCENARIOS = ("spiral", "rotation", "hover", "survey", "framedrop", "aggressive")
#: Frame windows rendered by default (20 Hz), chosen to hold each scenario's characteristic
#: motion while keeping the rendering time of the whole table near 45 min on 2 cores (640x480);
#: --full renders complete flights (about 4300 frames, 2-3 h).
WINDOWS = {"spiral": "0:300", "rotation": "40:280", "hover": "0:160", "survey": "0:200",
           "framedrop": "0:200", "aggressive": "0:160"}
ABLATIONS = {"": {}, " †": {"finest_level_only": True}, " ‡": {"current_frame_keyframe": True}}


def study_of(args) -> dict:
    """The study (decoded-TOML form) that the options describe."""
    variants = []
    configs = [("ours", "default")]
    if args.config:
        configs = [("ours" if p.stem == "mono_default" else p.stem, str(p.resolve())) for p in args.config]
    for name, config in configs:
        for suffix, flags in (ABLATIONS if args.ablations else {"": {}}).items():
            variants.append({"name": name + suffix, "config": config, **flags})
    if args.datasets:
        scenarios = [{"dataset": str(p.resolve()), "label": p.name} for p in args.datasets]
    else:
        scenarios = []
        for s in args.scenarios:
            entry = {"scenario": s}
            if not args.full and s in WINDOWS:
                entry["frames"] = WINDOWS[s]
            scenarios.append(entry)
    return {"name": "bench_vo", "description": "benchmarks/bench_vo.py " + " ".join(sys.argv[1:]),
            "delta": args.delta, "frames_per_task": 100,
            "render": {"width": args.width, "height": args.height, "threads": 1},
            "scenario": scenarios, "variant": variants}


def logging_cost(study, out: Path, delta: float) -> list[dict]:
    """Repeat each sequence's "ours" run with a rerun recording: logging time per frame."""
    from granite.cli.run_cmd import perform_run
    from granite.io import open_dataset

    costs = []
    ours = next((v for v in study.variants if v.name == "ours"), None)
    for seq in study.sequences if ours else ():
        folder = run_dir(out, seq, ours)
        if not (folder / "trajectory.tum").is_file():
            continue
        logged, _ = perform_run(open_dataset(seq.folder(out)), ours.build(), folder, folder / "recording.rrd",
                                delta=delta, progress=False, config_label=ours.label())
        n = len(logged.diagnostics)
        vo_ms = float(np.mean([d.processing_ms for d in logged.diagnostics]))
        log_ms = 1e3 * logged.logging_seconds / n
        costs.append({"scenario": seq.label, "vo_ms_per_frame": vo_ms, "logging_ms_per_frame": log_ms,
                      "startup_s": logged.logging_startup_seconds,
                      "recording_mb": (folder / "recording.rrd").stat().st_size / 1e6})
    return costs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("runs/bench"), help="study folder (default runs/bench)")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--ablations", action="store_true", help="also run † and ‡")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--delta", type=float, default=DEFAULT_RPE_DELTA)
    parser.add_argument("--config", type=Path, action="append",
                        help="configuration file (repeatable; default: the built-in defaults)")
    parser.add_argument("--datasets", type=Path, nargs="+",
                        help="run on these dataset folders instead of rendering the scenarios")
    parser.add_argument("--no-render", action="store_true", help="use only already rendered sequences")
    parser.add_argument("--full", action="store_true", help="render and run complete flights, not the windows")
    parser.add_argument("--rerun", action="store_true",
                        help="repeat 'ours' with a rerun recording and print the logging cost")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="local cluster worker processes (default: one per core)")
    where.add_argument("--scheduler", help="address of a running Dask scheduler")
    where.add_argument("--serial", action="store_true", help="no Dask: everything in this process")
    args = parser.parse_args()

    from granite.errors import GraniteError

    try:
        study = parse_study(study_of(args), Path("benchmarks/bench_vo.py"))
        if args.no_render:
            keep = tuple(s for s in study.sequences if not s.rendered or complete_marker(args.data, s).is_file())
            for s in study.sequences:
                if s not in keep:
                    print(f"{s.label}: not rendered, skipped")
            study = dataclasses.replace(study, sequences=keep)
            if not keep:
                return 0
        rows, failed = execute(study, args.data, args.scheduler, args.workers, args.serial)
    except GraniteError as error:
        print(f"bench_vo: error: {error}", file=sys.stderr)
        return 2
    costs = logging_cost(study, args.data, args.delta) if args.rerun else []

    frames = {s.id: s.frames for s in study.sequences}
    print(f"\n| scenario (frames) | variant | restarts | tracking % | RMS RPE (Δ={args.delta:g} s) [m] | ATE / path | VO fps |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        if r.get("status") != "ok":
            print(f"| {r['scenario']} ({frames[r['sequence']]}) | {r['variant']} | {r.get('status')} | | | | |")
            continue
        rpe = "n/a" if r["rpe_rmse"] is None else f"{r['rpe_rmse']:.3f}"
        ate = "n/a" if r["ate_over_path_length"] is None else f"{100 * r['ate_over_path_length']:.2f} %"
        fps = "n/a" if r["vo_fps"] is None else f"{r['vo_fps']:.1f}"
        print(f"| {r['scenario']} ({frames[r['sequence']]}) | {r['variant']} | {r['restarts']} | "
              f"{r['tracking_percentage']:.1f} | {rpe} | {ate} | {fps} |")
    for c in costs:
        print(f"logging cost {c['scenario']}: {c['logging_ms_per_frame']:.1f} ms/frame, "
              f"{100 * c['logging_ms_per_frame'] / c['vo_ms_per_frame']:.0f} % of the VO's frame time, "
              f"start-up {c['startup_s']:.1f} s, recording {c['recording_mb']:.0f} MB")
    report = {"rows": rows, "logging_cost": costs, "delta": args.delta,
              "configurations": {v.name: v.label() for v in study.variants}}
    (args.data / "bench_vo.json").write_text(json.dumps(report, indent=2) + "\n")
    print(f"study report: {args.data / 'report.md'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
