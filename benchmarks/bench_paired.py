"""Paired speed comparison of two VO variants on one dataset, robust to a drifting host (issue 15).

    python benchmarks/bench_paired.py DATASET [--rounds 10] [--frames N] [--mode conc|seq]
                                    [--config-a FILE] [--config-b FILE]
                                    [--tree-a DIR] [--tree-b DIR] [--json FILE]

A side is a source tree (``--tree-*``, a checkout or ``git worktree`` of granite-py; default
this checkout) with a VO configuration (``--config-*``; default the built-in defaults). Each
round runs both sides, one after the other, each in a fresh process that imports ``granite``
from its tree, loads the images into memory, makes a short warm-up run (its first 30 frames:
numba's cache loaded) and then times one run of the VO (``--mode conc``: the default concurrent
pipeline; ``seq``: ``--sequential``). The order alternates between rounds (A B, B A, ...), so a
trend of the host's speed does not favour one side.

Why: on a shared VM the same code runs up to 20 % slower or faster from one minute to the next
(docs/architecture.md), more than most single changes; two single runs compare nothing. What is
printed: per round each side's wall and CPU ms per frame, then per side the medians and the
median over rounds of the ratio B / A of wall and of CPU time (below 1: B is faster), and in how
many rounds B was faster; with each run the hypervisor's steal share of the CPU time during it
(``benchmarks/_host.py``; the cause of the host's drift on this VM). The poses checksum
(``float.hex`` of the sum of the absolute pose entries) of every run is compared: a variant that
should change no result (a scheduling or kernel change) must give the same checksum on both
sides, and every run of a side must give the same one (determinism); a mismatch is printed as a warning. ``--json`` keeps all runs.
Bad input (a dataset that cannot be opened, a tree without ``granite/``, an invalid
configuration, ``--rounds`` < 1) is a one-line error with exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _host  # noqa: E402  (benchmarks/_host.py)

ROOT = Path(__file__).resolve().parents[1]
WARMUP_FRAMES = 30


def worker(dataset_path: str, mode: str, frames: int | None, config_path: str | None) -> dict:
    """One timed run of one side, in this (fresh) process; ``granite`` comes from PYTHONPATH."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run`
    import numpy as np

    import granite
    from granite.estimator.config import VoConfig
    from granite.estimator.pipeline import VoPipeline
    from granite.estimator.vo import MonocularVO
    from granite.io import open_dataset

    config = VoConfig.load(config_path) if config_path else VoConfig()
    dataset = open_dataset(dataset_path)
    n = len(dataset) if frames is None else min(frames, len(dataset))
    loaded = list(dataset.frames(0, n))
    concurrent = mode == "conc"

    def run(items):
        vo = MonocularVO(dataset.calibration.camera(), config)
        vo.export_landmarks = True  # as `granite run`
        return [out.T_w_c for _, out in VoPipeline(vo, concurrent).run(items)]

    run(loaded[:WARMUP_FRAMES])
    ticks = _host.cpu_ticks()
    t0, c0 = time.perf_counter(), time.process_time()
    poses = run(loaded)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"granite": str(Path(granite.__file__).resolve().parent), "frames": n,
            "wall_ms": 1e3 * wall / n, "cpu_ms": 1e3 * cpu / n,
            "checksum": float(np.sum(np.abs(np.array(poses)))).hex(),
            **_host.shares(ticks, _host.cpu_ticks())}


def _check_inputs(args) -> str | None:
    """The first problem with the command line, or None."""
    if args.rounds < 1:
        return f"--rounds must be at least 1, got {args.rounds}"
    if args.frames is not None and args.frames <= WARMUP_FRAMES:
        return f"--frames must be more than the {WARMUP_FRAMES} warm-up frames, got {args.frames}"
    for side in "ab":
        tree = getattr(args, f"tree_{side}")
        if not (tree / "granite" / "__init__.py").is_file():
            return f"--tree-{side} {tree}: no granite package there (granite/__init__.py)"
    from granite.errors import GraniteError
    from granite.estimator.config import VoConfig
    from granite.io import open_dataset
    for side in "ab":
        path = getattr(args, f"config_{side}")
        if path is not None:
            try:
                VoConfig.load(path)
            except GraniteError as exc:
                return f"--config-{side}: {exc}"
    try:
        dataset = open_dataset(args.dataset)
    except GraniteError as exc:
        return str(exc)
    if len(dataset) <= WARMUP_FRAMES:
        return f"{args.dataset}: {len(dataset)} frames, need more than the {WARMUP_FRAMES} warm-up frames"
    return None


def run_side(args, side: str) -> dict:
    tree = getattr(args, f"tree_{side}").resolve()
    config = getattr(args, f"config_{side}")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(args.dataset.resolve()), args.mode]
    if args.frames:
        cmd += ["--frames", str(args.frames)]
    if config:
        cmd += ["--worker-config", str(Path(config).resolve())]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tree, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"side {side.upper()} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _steal(run: dict) -> str:
    """`` steal X %`` of a run (the hypervisor's share of the CPU time, :mod:`_host`), or ''."""
    return f" steal {run['steal_pct']:4.1f} %" if "steal_pct" in run else ""


def summarise(runs: list[dict]) -> dict:
    """Medians per side, paired ratios B / A, wins of B, checksum agreement."""
    a = [r["a"] for r in runs]
    b = [r["b"] for r in runs]
    wall = [y["wall_ms"] / x["wall_ms"] for x, y in zip(a, b)]
    cpu = [y["cpu_ms"] / x["cpu_ms"] for x, y in zip(a, b)]
    return {
        "rounds": len(runs),
        "a_wall_ms_median": statistics.median(x["wall_ms"] for x in a),
        "b_wall_ms_median": statistics.median(y["wall_ms"] for y in b),
        "a_cpu_ms_median": statistics.median(x["cpu_ms"] for x in a),
        "b_cpu_ms_median": statistics.median(y["cpu_ms"] for y in b),
        "wall_ratio_median": statistics.median(wall),
        "cpu_ratio_median": statistics.median(cpu),
        "b_faster_rounds": sum(1 for r in wall if r < 1.0),
        **_steal_summary([r for r in a + b if "steal_pct" in r]),
        "a_checksums": sorted({x["checksum"] for x in a}),
        "b_checksums": sorted({y["checksum"] for y in b}),
    }


def _steal_summary(runs: list[dict]) -> dict:
    steal = [r["steal_pct"] for r in runs]
    if not steal:
        return {"steal_pct_median": None, "steal_pct_min": None, "steal_pct_max": None}
    return {"steal_pct_median": statistics.median(steal), "steal_pct_min": min(steal),
            "steal_pct_max": max(steal)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 epilog="See the module docstring (the file's header) for the method.")
    ap.add_argument("dataset", type=Path, nargs="?", help="dataset folder (EuRoC/ASL layout)")
    ap.add_argument("--rounds", type=int, default=10, help="rounds of A and B (default 10)")
    ap.add_argument("--frames", type=int, default=None, help="first N frames only (default all)")
    ap.add_argument("--mode", choices=["conc", "seq"], default="conc",
                    help="concurrent pipeline (default) or the sequential loop")
    ap.add_argument("--config-a", default=None, help="VO configuration of side A (default: built-in)")
    ap.add_argument("--config-b", default=None, help="VO configuration of side B (default: built-in)")
    ap.add_argument("--tree-a", type=Path, default=ROOT, help="source tree of side A (default: this checkout)")
    ap.add_argument("--tree-b", type=Path, default=ROOT, help="source tree of side B (default: this checkout)")
    ap.add_argument("--json", type=Path, default=None, help="write every run and the summary here")
    ap.add_argument("--worker", nargs=2, metavar=("DATASET", "MODE"), help=argparse.SUPPRESS)
    ap.add_argument("--worker-config", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker[0], args.worker[1], args.frames, args.worker_config)))
        return 0
    if args.dataset is None:
        ap.error("the dataset is required")
    problem = _check_inputs(args)
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    print(f"A: {args.tree_a.resolve()} config {args.config_a or '(defaults)'}")
    print(f"B: {args.tree_b.resolve()} config {args.config_b or '(defaults)'}")
    print(f"{args.dataset}, mode {args.mode}, {args.rounds} rounds; load average {os.getloadavg()[0]:.1f}")
    runs = []
    try:
        for k in range(args.rounds):
            order = "ab" if k % 2 == 0 else "ba"
            result = {side: run_side(args, side) for side in order}
            runs.append(result)
            a, b = result["a"], result["b"]
            print(f"round {k + 1:2d} ({order.upper()}): A {a['wall_ms']:6.2f} ms wall {a['cpu_ms']:6.2f} ms CPU"
                  f"{_steal(a)} | B {b['wall_ms']:6.2f} wall {b['cpu_ms']:6.2f} CPU{_steal(b)} | "
                  f"B/A wall {b['wall_ms'] / a['wall_ms']:.3f}", flush=True)
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    s = summarise(runs)
    print(f"medians: A {s['a_wall_ms_median']:.2f} ms wall, {s['a_cpu_ms_median']:.2f} ms CPU per frame; "
          f"B {s['b_wall_ms_median']:.2f} / {s['b_cpu_ms_median']:.2f}")
    if s["steal_pct_median"] is not None:
        print(f"hypervisor steal during the timed runs: median {s['steal_pct_median']:.1f} %, "
              f"range {s['steal_pct_min']:.1f}-{s['steal_pct_max']:.1f} % of the CPU time")
    print(f"paired B / A, median over rounds: wall {s['wall_ratio_median']:.3f}, CPU {s['cpu_ratio_median']:.3f}; "
          f"B faster in {s['b_faster_rounds']} of {s['rounds']} rounds")
    for side in "ab":
        if len(s[f"{side}_checksums"]) > 1:
            print(f"WARNING: side {side.upper()} gave different trajectories in different rounds")
    if s["a_checksums"] == s["b_checksums"]:
        print(f"poses checksum: A and B identical ({s['a_checksums'][0]})")
    else:
        print(f"poses checksum: A {', '.join(s['a_checksums'])} differs from B {', '.join(s['b_checksums'])}")
    if args.json:
        tmp = args.json.with_name(args.json.name + ".tmp")
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps({"runs": runs, "summary": s}, indent=2) + "\n")
        tmp.replace(args.json)
        print(f"results: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
