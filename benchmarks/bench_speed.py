"""Speed and memory of the VO: sequential against concurrent (issue 15).

    python benchmarks/bench_speed.py [DATASET ...] [--repeats 2] [--frames N] [--json FILE]
                                     [--config FILE]

Default datasets: the 640x480 bench renders of this checkout
(``runs/bench/sequences/*_640x480_*``, made by ``python benchmarks/bench_vo.py``, and the older
``runs/bench/*_640x480_*``), if any, and ``assets/sequences/*``. Per dataset and mode (``seq``: ``granite run
--sequential``, one thread; ``conc``: the default concurrent pipeline,
:mod:`granite.estimator.pipeline`) a fresh process

1. runs ``run_vo`` as ``granite run`` does (images decoded from disk, per-frame records kept
   for ``landmarks.npz``; no evaluation, no files), which also warms the numba cache, and
   reads the peak RSS (``ru_maxrss``) after it; its frames/s are printed as ``run fps`` (what
   a user of ``granite run`` gets: image decoding and the kernels' loading from the cache
   included, no plots);
2. loads the images into memory and times the VO alone ``--repeats`` times (the best run is
   printed): wall ms per frame and frames/s, process CPU ms per frame (``time.process_time``),
   CPU utilisation = CPU time / wall time (1.0 = one core busy), and in the concurrent mode the
   CPU time of the caller's thread (the estimator; ``time.thread_time``) and the wall time it
   waited for the frontend (the tracking of the next frame) and for the previous frame's
   Λ_scaledrift (computed on the tracker's thread while the estimator works on the next frame).

Before the first dataset, one short run per mode (its first 40 frames, output discarded) fills
numba's cache, so that no row's peak RSS counts the compilation of the kernels (after a code
change a cold cache added about 55 MB to the concurrent spiral's peak).

On a loaded machine wall times (frames/s) depend on the other processes: the CPU times are the
figures to compare, and the load average is printed with each row. On a virtual machine they
also depend on the hypervisor: the last column is the steal share of all CPU time during the
best run (``benchmarks/_host.py``; 0-40 % on this project's VM between runs minutes apart in one
session, which slows the frame rate by about as much). Results also go to
``--json`` (default ``runs/bench/bench_speed.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run`

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _host  # noqa: E402  (benchmarks/_host.py)

ROOT = Path(__file__).resolve().parents[1]


def default_datasets() -> list[Path]:
    bench = ROOT / "runs" / "bench"
    found = sorted(p for p in [*bench.glob("*_640x480_*"), *bench.glob("sequences/*_640x480_*")]
                   if (p / "mav0").is_dir())
    found += sorted(p for p in (ROOT / "assets" / "sequences").iterdir() if (p / "mav0").is_dir())
    return found


def worker(dataset_path: str, mode: str, repeats: int, frames: int | None,
           config_path: str | None = None) -> dict:
    """One dataset in one mode, in this (fresh) process."""
    import numpy as np

    from granite.estimator.config import VoConfig
    from granite.estimator.pipeline import VoPipeline
    from granite.estimator.records import FrameRecord
    from granite.estimator.runner import run_vo
    from granite.estimator.vo import MonocularVO
    from granite.io import open_dataset

    concurrent = mode == "conc"
    config = VoConfig.load(config_path) if config_path else VoConfig()
    rss_start = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    dataset = open_dataset(dataset_path)
    n = len(dataset) if frames is None else min(frames, len(dataset))
    records = []
    t0, c0 = time.perf_counter(), time.process_time()
    run_vo(dataset, config, progress=False, max_frames=n, concurrent=concurrent,
           on_frame=lambda f, out: records.append(FrameRecord.from_output(f.index, f.timestamp, out)))
    run_wall, run_cpu = time.perf_counter() - t0, time.process_time() - c0
    rss_run = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    del records

    loaded = list(dataset.frames(0, n))
    best = None
    for _ in range(repeats):
        vo = MonocularVO(dataset.calibration.camera(), config)
        vo.export_landmarks = True  # as run_vo
        pipe = VoPipeline(vo, concurrent)
        ticks = _host.cpu_ticks()
        t0, c0, m0 = time.perf_counter(), time.process_time(), time.thread_time()
        poses = [out.T_w_c for _, out in pipe.run(loaded)]
        wall, cpu, main = time.perf_counter() - t0, time.process_time() - c0, time.thread_time() - m0
        host = _host.shares(ticks, _host.cpu_ticks())
        row = {**host, "wall_ms": 1e3 * wall / n, "cpu_ms": 1e3 * cpu / n, "utilisation": cpu / wall,
               "fps": n / wall, "caller_cpu_ms": 1e3 * (pipe.caller_cpu if concurrent else main) / n,
               "waited_tracker_ms": 1e3 * pipe.waited_tracker / n,
               "waited_scale_drift_ms": 1e3 * pipe.waited_scale_drift / n,
               "poses_checksum": float(np.sum(np.abs(np.array(poses))))}
        if best is None or row["wall_ms"] < best["wall_ms"]:
            best = row
    return {"dataset": str(dataset_path), "mode": mode, "frames": n, "size": f"{dataset.calibration.width}x"
            f"{dataset.calibration.height}", "run_ms": 1e3 * run_wall / n, "run_cpu_ms": 1e3 * run_cpu / n,
            "rss_start_mb": rss_start, "peak_rss_mb": rss_run, "load": os.getloadavg()[0], **best}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("datasets", nargs="*", type=Path)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--frames", type=int, help="first N frames only")
    parser.add_argument("--modes", nargs="+", default=["seq", "conc"], choices=["seq", "conc"])
    parser.add_argument("--json", type=Path, default=ROOT / "runs" / "bench" / "bench_speed.json")
    parser.add_argument("--config", help="VO configuration TOML (default: the built-in defaults)")
    parser.add_argument("--worker", nargs=2, metavar=("DATASET", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(args.worker[0], args.worker[1], args.repeats, args.frames, args.config)))
        return 0

    if args.config:
        from granite.errors import GraniteError
        from granite.estimator.config import VoConfig
        try:
            VoConfig.load(args.config)
        except GraniteError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    datasets = args.datasets or default_datasets()
    probe = _host.speed_probe()
    print(f"{os.cpu_count()} CPUs; load average at start {os.getloadavg()[0]:.1f}; "
          f"{_host.probe_text(probe)}")
    header = (f"{'dataset':34s} {'mode':4s} {'frames':>6s} {'fps':>6s} {'wall ms':>8s} {'CPU ms':>7s} "
              f"{'util':>5s} {'estim. CPU ms':>13s} {'waited ms':>9s} {'Λ wait ms':>9s} {'run fps':>7s} {'peak RSS MB':>11s} "
              f"{'load':>5s} {'steal %':>7s}")
    print(header)
    rows = []
    config = ["--config", str(Path(args.config).resolve())] if args.config else []
    if datasets:  # fill numba's cache first: the peak RSS of a row must not count compilation
        for mode in args.modes:
            subprocess.run([sys.executable, __file__, "--worker", str(datasets[0]), mode, "--repeats", "1",
                            "--frames", "40", *config], capture_output=True, text=True, cwd=ROOT)
    for ds in datasets:
        for mode in args.modes:
            cmd = [sys.executable, __file__, "--worker", str(ds), mode, "--repeats", str(args.repeats)]
            if args.frames:
                cmd += ["--frames", str(args.frames)]
            cmd += config
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            if proc.returncode != 0:
                print(f"{ds.name}: {mode} failed:\n{proc.stderr[-2000:]}")
                continue
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row["host_probe_ms_at_start"] = probe["probe_ms"]
            rows.append(row)
            waited = (f"{row['waited_tracker_ms']:9.2f} {row.get('waited_scale_drift_ms', 0.0):9.2f}"
                      if mode == "conc" else f"{'':9s} {'':9s}")
            print(f"{Path(row['dataset']).name + ' ' + row['size']:34s} {mode:4s} {row['frames']:6d} "
                  f"{row['fps']:6.1f} {row['wall_ms']:8.2f} {row['cpu_ms']:7.2f} {row['utilisation']:5.2f} "
                  f"{row['caller_cpu_ms']:13.2f} {waited} {1e3 / row['run_ms']:7.1f} {row['peak_rss_mb']:11.0f} "
                  f"{row['load']:5.1f} "
                  f"{row.get('steal_pct', float('nan')):7.1f}",
                  flush=True)
        pair = [r for r in rows if r["dataset"] == str(ds)]
        if len(pair) == 2 and pair[0]["poses_checksum"] != pair[1]["poses_checksum"]:
            print(f"  WARNING: {ds.name}: sequential and concurrent trajectories differ")
    print(f"at the end: {_host.probe_text(_host.speed_probe())}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(rows, indent=2) + "\n")
    print(f"results: {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
