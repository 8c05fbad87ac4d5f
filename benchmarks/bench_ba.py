"""Benchmark of one Gauss-Newton iteration of the sliding-window bundle adjustment.

Window of the reference size: 11 keyframes + 3 recent frames (14 poses), about 600 landmarks
and 3000 observations (synthetic scene, pinhole 640x480, 0.5 px noise). Prints milliseconds
per GN iteration (linearisation + landmark Schur complement + priors + dense 84x84 solve +
back-substitution + update) with a per-stage breakdown. Numba compilation is excluded: a
warm-up run is done first (kernels are cached on disk with ``cache=True``).

Usage: ``python benchmarks/bench_ba.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from granite.backend import BackendConfig, pose_delta  # noqa: E402
from granite.backend.synthetic import build_window, make_scene  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="timed optimize() calls")
    parser.add_argument("--iterations", type=int, default=7, help="GN iterations per call")
    args = parser.parse_args()

    scene = make_scene(num_frames=14, num_points=600, obs_per_landmark=6, recent_frames=3,
                       max_level=2, seed=0)
    config = BackendConfig(step_tolerance=0.0)  # never stop early: time full iterations
    length = float(np.linalg.norm(scene.poses[1][:3, 3] - scene.poses[0][:3, 3]))

    def fresh():
        win = build_window(scene, config, pose_noise=(0.01, 0.005), bearing_noise=0.001,
                           inv_dist_noise=0.1)
        win.set_scale_fix(scene.frame_ids[0], scene.frame_ids[1], length)
        return win

    t0 = time.perf_counter()
    fresh().optimize(max_iterations=2)  # warm-up: numba compile / cache load
    warmup = time.perf_counter() - t0

    win = fresh()
    n_obs = win.landmarks.num_observations
    print(f"window: {len(win.frame_ids)} poses ({len(win.keyframe_ids)} keyframes), "
          f"{len(win.landmarks)} landmarks, {n_obs} observations")
    print(f"warm-up (numba compile or cache load, excluded): {warmup:.2f} s")

    per_iter = []
    per_call = []
    stages: dict[str, float] = {}
    total_iters = 0
    for _ in range(args.repeats):
        win = fresh()
        t0 = time.perf_counter()
        report = win.optimize(max_iterations=args.iterations)
        dt = time.perf_counter() - t0
        per_call.append(dt)
        per_iter.append(sum(report.timings.values()) / report.iterations)
        total_iters += report.iterations
        for k, v in report.timings.items():
            stages[k] = stages.get(k, 0.0) + v
    ms = 1e3 * np.array(per_iter)
    print(f"GN iteration: {np.median(ms):.2f} ms median (min {ms.min():.2f}, max {ms.max():.2f})"
          f" over {args.repeats} x {args.iterations} iterations")
    print("  breakdown per iteration: " + ", ".join(
        f"{k} {1e3 * v / total_iters:.2f} ms" for k, v in stages.items()))
    call = 1e3 * np.array(per_call)
    print(f"optimize() call incl. packing and final cost: {np.median(call):.2f} ms median "
          f"for {args.iterations} iterations")
    print(f"final cost {report.final_cost:.1f} (initial {report.initial_cost:.1f})")
    accuracy(scene, length)
    return 0


def accuracy(scene, length: float) -> None:
    """Accuracy against the synthetic truth: least squares (no Huber) to convergence, errors
    compared with the covariance predicted by the window Hessian (paper Eq. 11)."""
    win = build_window(scene, BackendConfig(huber_threshold=1e6, step_tolerance=1e-10),
                       pose_noise=(0.03, 0.01), bearing_noise=0.003, inv_dist_noise=0.3)
    win.set_scale_fix(scene.frame_ids[0], scene.frame_ids[1], length)
    report = win.optimize(max_iterations=20)
    e = np.concatenate([pose_delta(win.pose(f), scene.pose_of(f)) for f in scene.frame_ids])
    cov = np.linalg.inv(win.hessian_blocks().H)[6:, 6:]
    nees = float(e[6:] @ np.linalg.solve(cov, e[6:]))
    err = e.reshape(-1, 6)[1:]
    n_obs = win.landmarks.num_observations
    dof = 2 * n_obs - (3 * len(win.landmarks) + 6 * len(win.frame_ids) - 7)
    pred_t = np.sqrt(np.mean(np.diag(cov).reshape(-1, 6)[:, :3].sum(axis=1)))
    pred_r = np.sqrt(np.mean(np.diag(cov).reshape(-1, 6)[:, 3:].sum(axis=1)))
    print(f"accuracy (sigma {scene.sigma} px, levels 0-2, start 3 cm / 0.6 deg off, "
          f"{report.iterations} GN iterations):")
    print(f"  RMS translation error {1e3 * np.sqrt(np.mean(np.sum(err[:, :3] ** 2, 1))):.2f} mm"
          f" (predicted {1e3 * pred_t:.2f} mm), RMS rotation error "
          f"{np.degrees(np.sqrt(np.mean(np.sum(err[:, 3:] ** 2, 1)))):.4f} deg "
          f"(predicted {np.degrees(pred_r):.4f} deg)")
    print(f"  pose NEES {nees:.1f} for {e.size - 7} dof; final cost / residual dof "
          f"{report.final_cost / dof:.3f} (chi-square, expected 1)")


if __name__ == "__main__":
    raise SystemExit(main())
