"""What each tracking pass of the frontend contributes inside the VO: tracks, time, accuracy.

    python benchmarks/bench_track_passes.py DATASET [DATASET ...] [--every 4] [--config FILE]

The VO runs sequentially (``granite run --sequential``) with the built-in defaults or
``--config``. Every ``--every``-th frame, the frontend's main tracking call (the one after the
probe tracks, :func:`granite.optical_flow.tracking.track_points`) is replayed on copies of its
inputs with the first 1, 2, ... passes of its pass order (fine guided, near guided, guided
through the whole pyramid, zero motion, median flow: docs/optical_flow.md), every lost track
allowed into every pass (``fallback=None``, as with ``[optical_flow] retry_out_of_view =
true``), and the minimum thread CPU time of 2 repetitions per prefix is taken. Per pass it
prints the tracks it adds per frame, its CPU time per frame and, where the dataset has depth
maps (the test-bench renders), the error of the tracks it adds against the ground-truth flow
(median, share beyond 2 px). Then, for the tracks the guided passes lost: how many per frame
were predicted outside the image in frames whose predictions the probes confirmed (the ones
``retry_out_of_view = false`` keeps out of the zero-motion and median passes), how many of
those the two passes found, and how many of the others.

The VO itself runs unchanged (the replays work on copies), so its trajectory is that of
``granite run``. Bad input (a missing dataset, an unreadable configuration) is one error line
and exit status 2.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run`

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

PASS_NAMES = {0: "zero motion", 1: "guided, whole pyramid", 2: "median flow", 3: "local flow",
              4: "guided, creation level", 5: "guided, level above"}


def _copy(x):
    if isinstance(x, np.ndarray):
        return np.array(x, copy=True)
    if isinstance(x, (tuple, list)):
        return type(x)(_copy(y) for y in x)
    return x


def measure(path: Path, every: int, config_path: str | None) -> dict:
    """Replay the main tracking calls of one VO run (see the module docstring)."""
    import granite.optical_flow.frame_to_frame as ff
    from bench_flow import _depth_loader
    from granite.estimator.config import VoConfig
    from granite.estimator.vo import MonocularVO
    from granite.geometry import interpolate_poses
    from granite.io import open_dataset
    from granite.optical_flow.gt_flow import ground_truth_flow

    ds = open_dataset(path)
    config = VoConfig.load(config_path) if config_path else VoConfig()
    camera = ds.calibration.camera()
    depth = _depth_loader(ds) if ds.ground_truth is not None else None
    state = {"frame": -1, "prev": None, "confirmed": False}
    calls = []
    track_points, correction = ff.track_points, ff.prediction_correction

    def recorded_correction(*args, **kwargs):
        H = correction(*args, **kwargs)
        state["confirmed"] = H is not None
        return H

    def replayed_track_points(*args, **kwargs):
        if kwargs.get("preset") is not None and state["frame"] % every == 0 and state["prev"] is not None:
            calls.append(_replay(track_points, args, kwargs, state, depth, ds, camera, ground_truth_flow,
                                 interpolate_poses))
        return track_points(*args, **kwargs)

    ff.track_points, ff.prediction_correction = replayed_track_points, recorded_correction
    poses = []
    try:
        vo = MonocularVO(camera, config)
        for frame in ds.frames(0, len(ds)):
            state["frame"] = frame.index
            state["t"] = frame.timestamp
            state["confirmed"] = False
            out = vo.process(frame.index, frame.timestamp, frame.image)
            if out.T_w_c is not None:
                poses.append(out.T_w_c)
            if frame.image is not None:
                state["prev"], state["t_prev"] = frame.index, frame.timestamp
    finally:
        ff.track_points, ff.prediction_correction = track_points, correction
    return {"dataset": path.name, "calls": calls, "poses": np.array(poses)}


def _replay(track_points, args, kwargs, state, depth, ds, camera, ground_truth_flow, interpolate_poses):
    """One tracking call replayed with growing prefixes of its pass order (copies of its inputs)."""
    from granite.optical_flow.frame_to_frame import predicted_out_of_view

    points = args[8]
    kwargs = {k: v for k, v in kwargs.items() if k not in ("executor", "share", "fallback")}
    order = [int(m) for m in kwargs["order"]]
    truth, known = None, np.zeros(len(points), dtype=bool)
    if depth is not None:
        poses = interpolate_poses(ds.ground_truth.timestamps, ds.ground_truth.poses,
                                  np.array([state["t_prev"], state["t"]]))
        truth, known = ground_truth_flow(points, depth(state["prev"]), poses[0], poses[1], camera)
    prefixes = []
    for m in range(1, len(order) + 1):
        best, result = np.inf, None
        for _ in range(2):
            a, k = _copy(list(args)), _copy(kwargs)
            k["order"] = np.array(order[:m], dtype=np.int64)
            t = time.thread_time()
            result = track_points(*a, **k)
            best = min(best, time.thread_time() - t)
        prefixes.append((best, result[0], result[2]))
    width, height = int(args[2][0]), int(args[3][0])
    predicted = points + kwargs["guess"]
    return {"order": order, "prefixes": prefixes, "truth": truth, "known": known, "predicted": predicted,
            "out_of_view": predicted_out_of_view(predicted, width, height), "size": (width, height),
            "confirmed": state["confirmed"]}


def report(result: dict) -> list[str]:
    calls = result["calls"]
    if not calls:
        return [f"{result['dataset']}: no guided tracking call with probes to replay"]
    lines = [f"{result['dataset']}: {len(calls)} replayed frames, {np.mean([len(c['out_of_view']) for c in calls]):.0f} "
             f"tracks per frame, predictions confirmed by the probes in {np.mean([c['confirmed'] for c in calls]):.0%} of them",
             "", "| pass | tracks added per frame | CPU ms per frame | GT error median [px] | GT error > 2 px |",
             "| --- | ---: | ---: | ---: | ---: |"]
    orders = {tuple(c["order"]) for c in calls}
    if len(orders) != 1:
        lines.append(f"(pass orders differ between frames: {sorted(orders)}; rows by position)")
    order = calls[0]["order"]
    for m, mode in enumerate(order):
        added, ms, errors = [], [], []
        for c in calls:
            t, pos, ok = c["prefixes"][m]
            t0, _, ok0 = c["prefixes"][m - 1] if m else (0.0, None, np.zeros_like(ok))
            new = ok & ~ok0
            added.append(new.sum())
            ms.append(1e3 * (t - t0))
            sel = new & c["known"]
            if c["truth"] is not None and sel.any():
                errors.append(np.linalg.norm(pos[sel] - c["truth"][sel], axis=1))
        e = np.concatenate(errors) if errors else np.zeros(0)
        gt = (f"{np.median(e):.3f} | {np.mean(e > 2.0):.3f}" if len(e) else "- | -")
        lines.append(f"| {PASS_NAMES.get(mode, mode)} | {np.mean(added):.2f} | {np.mean(ms):.2f} | {gt} |")
    guided = [i for i, mode in enumerate(order) if mode in (1, 4, 5)]
    blind = [i for i, mode in enumerate(order) if mode in (0, 2)]
    if guided and blind:
        g, b = max(guided), max(blind)
        lost, away, found_away, found_in = [], [], [], []
        for c in calls:
            lost_g = ~c["prefixes"][g][2]
            gate = c["out_of_view"] & c["confirmed"]
            found = c["prefixes"][b][2] & lost_g
            lost.append(lost_g.sum())
            away.append((lost_g & gate).sum())
            found_away.append((found & gate).sum())
            found_in.append((found & ~gate).sum())
        lines += ["", f"tracks lost by the guided passes per frame {np.mean(lost):.2f}; of them predicted outside "
                  f"the image in confirmed frames {np.mean(away):.2f}, of which the zero-motion and median passes "
                  f"found {np.mean(found_away):.2f}; they found {np.mean(found_in):.2f} of the others"]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("datasets", nargs="+", type=Path)
    parser.add_argument("--every", type=int, default=4, help="replay every N-th frame (default 4)")
    parser.add_argument("--config", help="VO configuration TOML (default: the built-in defaults)")
    args = parser.parse_args()
    from granite.errors import GraniteError
    from granite.estimator.config import VoConfig
    from granite.io import open_dataset
    try:
        if args.every < 1:
            raise GraniteError(f"--every must be at least 1, got {args.every}")
        if args.config:
            VoConfig.load(args.config)
        for path in args.datasets:
            open_dataset(path)
    except GraniteError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in args.datasets:
        print("\n".join(report(measure(path, args.every, args.config))) + "\n", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
