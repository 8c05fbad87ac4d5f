"""Benchmark of the sliding-window bundle adjustment: per GN iteration and per frame.

1. One Gauss-Newton iteration on a window of the reference size: 11 keyframes + 3 recent
   frames (14 poses), about 600 landmarks and 3000 observations (synthetic scene, pinhole
   640x480, 0.5 px noise). Prints milliseconds per GN iteration (linearisation + landmark Schur
   complement + priors + dense 84x84 solve + back-substitution + update) with a per-stage
   breakdown, and the whole ``optimize()`` call (packing, final cost, write-back included).
2. Per frame, the backend calls the VO pipeline makes on a sliding synthetic sequence (every
   second frame a keyframe, ~80 new landmarks per keyframe, steady window of 11 keyframes +
   3 frames with ~900 landmarks / ~5000 observations): ``add_frame``, ``add_landmark``, one
   ``add_observation`` per observation (or one ``add_observations`` batch with ``--batch``),
   ``optimize(snapshot_iteration=3)`` + negative entropy, ``num_connected`` (3x),
   ``remove_outliers``, ``frames_to_marginalize`` (estimator policy) + ``marginalize``. Prints the
   median milliseconds per frame over the steady-state frames with a per-call breakdown.

Numba compilation is excluded: a warm-up run is done first (kernels are cached on disk with
``cache=True``).

Usage: ``python benchmarks/bench_ba.py [--repeats N] [--batch] [--no-sequence]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from granite.backend import BackendConfig, SlidingWindow, pose_delta  # noqa: E402
from granite.backend.synthetic import build_window, make_scene  # noqa: E402
from granite.estimator.window_policy import frames_to_marginalize  # noqa: E402
from granite.geometry import decoupled_increment  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="timed optimize() calls")
    parser.add_argument("--iterations", type=int, default=7, help="GN iterations per call")
    parser.add_argument("--batch", action="store_true",
                        help="per-frame benchmark: add observations with add_observations()")
    parser.add_argument("--no-sequence", action="store_true",
                        help="skip the per-frame benchmark (it builds a 50-frame scene, ~3 s)")
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
    if not args.no_sequence:
        per_frame(args.batch)
    return 0


def per_frame(batch: bool) -> None:
    """Backend time per frame with the call pattern of the VO pipeline on a sliding sequence."""
    scene = make_scene(num_frames=50, num_points=2000, obs_per_landmark=10, keyframe_every=2,
                       max_level=2, baseline=0.1, seed=0)
    hosted: dict[int, list[int]] = {}
    for i, lm_id in enumerate(scene.lm_ids):
        hosted.setdefault(scene.lm_host[i], []).append(i)
    by_frame: dict[int, list] = {}
    for obs in scene.observations:
        by_frame.setdefault(obs[1], []).append(obs)
    rng = np.random.default_rng(7)
    warmup = 16  # frames before the window is full (not timed)

    def run() -> tuple[list[dict[str, float]], list[tuple[int, int, int]]]:
        win = SlidingWindow(scene.camera, BackendConfig())
        frames, sizes = [], []
        for k, fid in enumerate(scene.frame_ids):
            t: dict[str, float] = {}
            t0 = time.perf_counter()
            T = scene.poses[k] if k == 0 else decoupled_increment(
                scene.poses[k], np.concatenate([rng.normal(0, 0.005, 3),
                                                rng.normal(0, 0.002, 3)]))
            win.add_frame(fid, T, is_keyframe=scene.keyframe[k])
            for i in hosted.get(fid, ()):
                win.add_landmark(scene.lm_ids[i], fid, scene.lm_bearing[i],
                                 scene.lm_inv_dist[i] * (1.0 + rng.normal(0, 0.05)))
            t1 = time.perf_counter()
            rows = by_frame.get(fid, [])
            if batch:
                win.add_observations(fid, [o[0] for o in rows], np.array([o[2] for o in rows]),
                                     [o[3] for o in rows], skip_unknown=True)
            else:
                db = win.landmarks
                for lm_id, f, uv, level in rows:
                    if lm_id in db:
                        win.add_observation(lm_id, f, uv, level)
            if k == 1:
                win.set_scale_fix(scene.frame_ids[0], fid, float(np.linalg.norm(
                    scene.poses[1][:3, 3] - scene.poses[0][:3, 3])))
            t2 = time.perf_counter()
            report = win.optimize(snapshot_iteration=3)
            report.snapshot.negative_entropy(fid)
            t3 = time.perf_counter()
            for _ in range(3):
                win.num_connected(fid)
            win.remove_outliers()
            t4 = time.perf_counter()
            sizes.append((len(win.frame_ids), len(win.landmarks),
                          win.landmarks.num_observations))
            win.marginalize(frames_to_marginalize(win, win.config))
            t5 = time.perf_counter()
            t.update(add_frame_landmarks=t1 - t0, add_observations=t2 - t1,
                     optimize=t3 - t2, connected_outliers=t4 - t3, marginalize=t5 - t4,
                     total=t5 - t0, iterations=report.iterations)
            frames.append(t)
        return frames[warmup:], sizes[warmup:]

    run()  # warm-up
    frames, sizes = run()
    sizes_arr = np.array(sizes)
    mode = "one add_observations() batch" if batch else "add_observation() per observation"
    print(f"per frame ({len(frames)} steady-state frames, {mode}): window "
          f"{sizes_arr[:, 0].mean():.1f} poses, {sizes_arr[:, 1].mean():.0f} landmarks, "
          f"{sizes_arr[:, 2].mean():.0f} observations on average")
    total = 1e3 * np.array([f["total"] for f in frames])
    iters = np.mean([f["iterations"] for f in frames])
    print(f"  backend per frame: {np.median(total):.2f} ms median (min {total.min():.2f}, "
          f"max {total.max():.2f}), {iters:.1f} GN iterations per optimize()")
    print("  breakdown (median ms): " + ", ".join(
        f"{k} {1e3 * np.median([f[k] for f in frames]):.2f}" for k in frames[0]
        if k not in ("total", "iterations")))


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
