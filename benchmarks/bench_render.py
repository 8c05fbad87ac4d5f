"""Seconds per 640x480 frame of the spiral scenario (Cycles CPU, the scenario's clean-quality
settings: 4 samples, no denoiser, direct sun + analytic sky light).

    python benchmarks/bench_render.py [--frames 8] [--samples N] [--corners] [--save DIR]

Prints the wall time per frame (after one warm-up frame that builds the BVH), the process CPU
time per frame divided by the render threads (what the time would be on an idle machine),
and the load average (the machine may be shared). ``--corners`` also prints the number of
FAST corners (OpenCV, threshold 20) per frame and its altitude; ``--save`` writes the frames.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def _cpu() -> float:
    u = resource.getrusage(resource.RUSAGE_SELF)
    return u.ru_utime + u.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=8, help="timed frames (spread over the flight)")
    ap.add_argument("--samples", type=int, default=None, help="override render.samples")
    ap.add_argument("--corners", action="store_true", help="FAST corners per altitude")
    ap.add_argument("--save", type=Path, default=None, help="write the frames as PNG here")
    args = ap.parse_args()

    from simulation.imaging import to_8bit
    from simulation.plan import make_plan
    from simulation.render import Renderer, software_versions
    from simulation.scenario import load_scenario, with_overrides
    from simulation.terrain.scene import build_world

    s = with_overrides(load_scenario("spiral"), width=640, height=480, samples=args.samples)
    t0 = time.perf_counter()
    plan = make_plan(s)
    t_plan = time.perf_counter() - t0
    t0 = time.perf_counter()
    build_world(s, plan.model)
    t_build = time.perf_counter() - t0
    n = len(plan.times)
    # the first half of the spiral climbs from 4 m to 40 m: sample it evenly
    idx = np.linspace(0, n // 2, args.frames + 1).round().astype(int)
    walls, cpus = [], []
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    with Renderer(s) as renderer:
        renderer.render(plan.poses[idx[0]])  # warm-up: BVH, shaders, images
        for i in idx[1:]:
            w0, c0 = time.perf_counter(), _cpu()
            rgb, _ = renderer.render(plan.poses[i])
            walls.append(time.perf_counter() - w0)
            cpus.append((_cpu() - c0) / s.render.threads)
            img = to_8bit(rgb, s.render.exposure)
            p = plan.poses[i][:3, 3]
            alt = p[2] - float(plan.model.ground_height(p[0], p[1]))
            line = f"frame {i:5d}  altitude {alt:5.1f} m  {walls[-1]:.2f} s"
            if args.corners:
                gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
                corners = len(cv2.FastFeatureDetector_create(20).detect(gray))
                line += f"  FAST corners {corners}"
            print(line, flush=True)
            if args.save:
                cv2.imwrite(str(args.save / f"spiral_{i:05d}.png"), img[..., ::-1])
    v = software_versions()
    print(f"Blender {v['blender']}, {s.render.threads} threads, {s.render.samples} samples, "
          f"640x480; plan {t_plan:.1f} s, scene build {t_build:.1f} s; load average "
          f"{os.getloadavg()[0]:.2f}")
    print(f"seconds per 640x480 frame: mean {np.mean(walls):.2f}, median {np.median(walls):.2f}"
          f" (wall); CPU / threads: mean {np.mean(cpus):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
