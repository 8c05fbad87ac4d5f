"""Paired render-time comparison of two source trees, robust to a drifting host (issue 15).

    python benchmarks/bench_render_paired.py --tree-a DIR [--tree-b DIR] [--frames 150,300,...]
                                             [--repeats 2] [--rounds 2]
                                             [--scenario spiral] [--size 640x480]

Each round starts two fresh processes side by side, one per tree (a checkout or ``git
worktree`` of granite-py; ``--tree-b`` defaults to this checkout), each rendering the same
frames (default: the spiral at 640x480) with one Cycles thread: both build the scene, wait for each other, then
render the frames (``--repeats`` times), so every frame of A is timed while B renders the same
frame in the same phase of the host. The sides swap their start order in alternate rounds.

Why: on this shared VM the same render takes from 1.0 to 1.3 s per frame from one minute to
the next, more than most changes save; alternated single runs need many rounds to see 5-10 %,
while the per-frame ratio of two renders running at the same time shows it in one. Printed per
round: the mean seconds per frame of each side (one thread: about twice a two-thread render)
and the median and mean per-frame ratio B / A (below 1: B is faster); then whether the two
trees rendered the same images (largest absolute difference of Cycles' linear radiance).
Bad input (a tree without ``simulation/``, an unknown scenario or frame, a malformed
``--size``, ``--rounds`` < 1) is a one-line error with exit status 2.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BARRIER_TIMEOUT = 600.0  #: seconds a side waits for the other to finish building its scene


def _scenario(name: str, width: int, height: int):
    from simulation.scenario import load_scenario, with_overrides

    return with_overrides(load_scenario(name), width=width, height=height)


def worker(scenario: str, width: int, height: int, frames: list[int], repeats: int,
           barrier: Path, out: Path) -> int:
    """Render ``frames`` with one thread in this process (``simulation`` from PYTHONPATH)."""
    import dataclasses

    from simulation.plan import make_plan
    from simulation.render import Renderer
    from simulation.terrain.scene import build_world

    s = _scenario(scenario, width, height)
    s = dataclasses.replace(s, render=dataclasses.replace(s.render, threads=1))
    plan = make_plan(s)
    build_world(s, plan.model)
    seconds, images = [], {}
    with Renderer(s) as renderer:
        renderer.render(plan.poses[frames[0]])  # warm-up: BVH, shaders, images
        (barrier / f"ready_{os.getpid()}").touch()
        deadline = time.monotonic() + BARRIER_TIMEOUT
        while len(list(barrier.glob("ready_*"))) < 2:
            if time.monotonic() > deadline:
                print("the other side never got ready", file=sys.stderr)
                return 1
            time.sleep(0.02)
        for _ in range(repeats):
            for i in frames:
                t = time.perf_counter()
                rgb, _ = renderer.render(plan.poses[i])
                seconds.append(time.perf_counter() - t)
                images[str(i)] = rgb
    np.savez(out, seconds=np.array(seconds), **{f"rgb_{k}": v for k, v in images.items()})
    return 0


def _round(trees: dict[str, Path], order: list[str], job: list[str], scratch: Path,
           k: int) -> dict[str, dict]:
    barrier = scratch / f"barrier_{k}"
    barrier.mkdir()
    procs = {}
    for side in order:
        out = scratch / f"round{k}_{side}.npz"
        log = scratch / f"round{k}_{side}.log"
        env = dict(os.environ, PYTHONPATH=str(trees[side]))
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", *job, str(barrier),
               str(out)]
        with open(log, "w") as err:
            proc = subprocess.Popen(cmd, env=env, cwd=trees[side], stdout=subprocess.DEVNULL,
                                    stderr=err)
        procs[side] = (proc, out, log)

    def failed() -> list[str]:
        return [side for side, (proc, _, _) in procs.items() if proc.poll() not in (None, 0)]

    # poll both: a side that fails leaves the other waiting at the barrier
    while not failed() and any(proc.poll() is None for proc, _, _ in procs.values()):
        time.sleep(0.1)
    bad = failed()
    if bad:
        for proc, _, _ in procs.values():
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        side = bad[0]
        last = (procs[side][2].read_text().strip().splitlines() or ["no message"])[-1]
        raise RuntimeError(f"side {side} ({trees[side]}) failed: {last}")
    return {side: dict(np.load(out)) for side, (_, out, _) in procs.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tree-a", type=Path, required=True, help="source tree of side A")
    ap.add_argument("--tree-b", type=Path, default=ROOT, help="source tree of side B")
    ap.add_argument("--frames", default="150,300,450,600",
                    help="spiral frames to render (comma-separated; default 9-40 m altitude)")
    ap.add_argument("--repeats", type=int, default=2, help="renders of the frame list per round")
    ap.add_argument("--rounds", type=int, default=2, help="rounds (start order alternates)")
    ap.add_argument("--scenario", default="spiral", help="bundled scenario name or .toml path")
    ap.add_argument("--size", default="640x480", help="image size WxH (intrinsics rescaled)")
    args = ap.parse_args(argv)
    trees = {"A": args.tree_a.resolve(), "B": args.tree_b.resolve()}
    for side, tree in trees.items():
        if not (tree / "simulation" / "render.py").is_file():
            print(f"error: --tree-{side.lower()} {tree} holds no simulation/render.py",
                  file=sys.stderr)
            return 2
    try:
        frames = [int(f) for f in args.frames.split(",")]
    except ValueError:
        print(f"error: --frames: expected comma-separated integers, got {args.frames!r}",
              file=sys.stderr)
        return 2
    if args.rounds < 1 or args.repeats < 1:
        print("error: --rounds and --repeats must be at least 1", file=sys.stderr)
        return 2
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"error: --size: expected WxH, got {args.size!r}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(ROOT))
    from granite.errors import ConfigError
    from simulation.plan import make_plan

    try:
        scenario = _scenario(args.scenario, width, height)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    n = len(make_plan(scenario).times)
    if any(not 0 <= f < n for f in frames):
        print(f"error: --frames: {scenario.name} has frames 0..{n - 1}", file=sys.stderr)
        return 2
    job = [args.scenario, str(width), str(height), ",".join(map(str, frames)), str(args.repeats)]
    ratios, largest = [], 0.0
    with tempfile.TemporaryDirectory(prefix="granite-render-paired-") as tmp:
        for k in range(args.rounds):
            order = ["A", "B"] if k % 2 == 0 else ["B", "A"]
            try:
                r = _round(trees, order, job, Path(tmp), k)
            except RuntimeError as e:
                print(f"error: {e}", file=sys.stderr)
                return 1
            a, b = r["A"]["seconds"], r["B"]["seconds"]
            ratio = b / a
            ratios.extend(ratio.tolist())
            print(f"round {k + 1} (started {order[0]} first): A {a.mean():.2f} s/frame, "
                  f"B {b.mean():.2f} s/frame (one thread); B / A median {np.median(ratio):.3f}"
                  f", mean {b.sum() / a.sum():.3f}", flush=True)
            for key in r["A"]:
                if key.startswith("rgb_"):
                    largest = max(largest, float(np.abs(r["A"][key] - r["B"][key]).max()))
    print(f"B / A over {len(ratios)} paired frames: median {np.median(ratios):.3f} "
          f"(quartiles {np.percentile(ratios, 25):.3f}-{np.percentile(ratios, 75):.3f})")
    print("images: identical" if largest == 0 else
          f"images: differ (largest difference {largest:.3g} in linear radiance)")
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 9 and sys.argv[1] == "--worker":
        name, w, h, fr, reps, barrier_dir, out_file = sys.argv[2:]
        sys.exit(worker(name, int(w), int(h), [int(f) for f in fr.split(",")], int(reps),
                        Path(barrier_dir), Path(out_file)))
    sys.exit(main())
