"""Seconds per 640x480 frame of the spiral scenario (Cycles CPU, the scenario's clean-quality
settings: 4 samples, no denoiser, direct sun + analytic sky light).

    python benchmarks/bench_render.py [--frames 8] [--samples N] [--corners] [--save DIR]
                                      [--plain-terrain]

Prints the wall time per frame (after one warm-up frame that builds the BVH), the process CPU
time per frame divided by the render threads (what the time would be on an idle machine),
the time of the sensor model per frame, and the load average (the machine may be shared).
``--plain-terrain`` renders the terrain of before the realism work (no ripples, power-law
rocks from 0.1 m) for an A/B comparison of the appearance cost in the same conditions. ``--corners`` also prints the number of
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
    ap.add_argument("--plain-terrain", action="store_true",
                    help="no ripples, power-law rocks (the terrain before the realism work)")
    args = ap.parse_args()

    import dataclasses

    from simulation.plan import make_plan
    from simulation.render import Renderer, software_versions
    from simulation.scenario import load_scenario, with_overrides
    from simulation.terrain.scene import build_world

    from simulation.sensor import Sensor, blur_taps

    s = with_overrides(load_scenario("spiral"), width=640, height=480, samples=args.samples)
    if args.plain_terrain:
        s = dataclasses.replace(s, terrain=dataclasses.replace(
            s.terrain, ripple_coverage=0.0, rock_model="power_law", rock_min_diameter=0.1))
    sensor = Sensor(s.sensor, s.camera, s.seed, True, s.render.exposure)
    t0 = time.perf_counter()
    plan = make_plan(s)
    t_plan = time.perf_counter() - t0
    t0 = time.perf_counter()
    build_world(s, plan.model)
    t_build = time.perf_counter() - t0
    n = len(plan.times)
    # the first half of the spiral climbs from 4 m to 40 m: sample it evenly
    idx = np.linspace(0, n // 2, args.frames + 1).round().astype(int)
    walls, cpus, sensor_ms = [], [], []
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    with Renderer(s) as renderer:
        renderer.render(plan.poses[idx[0]])  # warm-up: BVH, shaders, images
        for i in idx[1:]:
            w0, c0 = time.perf_counter(), _cpu()
            rgb, depth = renderer.render(plan.poses[i])
            walls.append(time.perf_counter() - w0)
            cpus.append((_cpu() - c0) / s.render.threads)
            w0 = time.perf_counter()
            e = s.sensor.exposure_time
            taps = blur_taps(depth, s.camera, plan.poses[i], plan.exposure_poses(i, e, 2))
            img, _ = sensor.capture(rgb, int(i), depth, plan.poses[i],
                                    plan.exposure_poses(i, e, taps) if sensor.blurs else None)
            sensor_ms.append(1e3 * (time.perf_counter() - w0))
            p = plan.poses[i][:3, 3]
            alt = p[2] - float(plan.model.ground_height(p[0], p[1]))
            line = f"frame {i:5d}  altitude {alt:5.1f} m  {walls[-1]:.2f} s"
            if args.corners:
                corners = len(cv2.FastFeatureDetector_create(20).detect(img))
                line += f"  FAST corners {corners}"
            print(line, flush=True)
            if args.save:
                cv2.imwrite(str(args.save / f"spiral_{i:05d}.png"), img)
    v = software_versions()
    print(f"Blender {v['blender']}, {s.render.threads} threads, {s.render.samples} samples, "
          f"640x480; plan {t_plan:.1f} s, scene build {t_build:.1f} s; load average "
          f"{os.getloadavg()[0]:.2f}")
    print(f"seconds per 640x480 frame: mean {np.mean(walls):.2f}, median {np.median(walls):.2f}"
          f" (wall); CPU / threads: mean {np.mean(cpus):.2f}; sensor model "
          f"{np.mean(sensor_ms):.0f} ms (grayscale)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
