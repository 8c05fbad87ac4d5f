"""Where a frame's CPU time goes: the sequential VO per stage (issue 15).

    python benchmarks/profile_vo.py DATASET [--frames N] [--repeats 3] [--cprofile OUT.prof]
                                         [--config FILE]

Loads the frames into memory and runs the VO as ``benchmarks/bench_speed.py`` does in its
sequential mode (``VoPipeline(vo, concurrent=False)``, landmarks exported as ``granite run``
does), once to warm the numba cache, then ``--repeats`` times. Per run it prints the process CPU
time per frame (``time.process_time``; on a shared machine the figure to compare, wall time
lies), the wall time, the minor page faults per frame, the load average, and the thread CPU time
per frame of each stage: functions of the frontend and the estimator wrapped with
``time.thread_time`` (nested stages overlap: ``estimate (total)`` contains
``window.optimize``, which contains ``schur_reduce`` ...; the wrappers' own timer calls are
included). Every run must give the same poses as the first (checked), and the last line prints
a checksum of them (``float.hex`` of the sum of the absolute pose entries) to compare code
versions quickly; ``tools/compare_runs.py`` compares the run folders byte for byte.
``--cprofile`` profiles the first timed run instead of timing it.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import resource
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `granite run`

import numpy as np  # noqa: E402

STAGE: dict[str, float] = {}


def wrap(owner, name: str, label: str) -> None:
    """Replace ``owner.name`` by a wrapper adding its thread CPU time to ``STAGE[label]``."""
    f = getattr(owner, name)

    def timed(*args, **kwargs):
        t = time.thread_time()
        try:
            return f(*args, **kwargs)
        finally:
            STAGE[label] = STAGE.get(label, 0.0) + time.thread_time() - t

    setattr(owner, name, timed)


def install_stage_timers() -> None:
    import granite.backend.hessian as hs
    import granite.backend.landmarks as lm
    import granite.backend.linearization as lin
    import granite.backend.problem as pb
    import granite.backend.scale_drift as sd
    import granite.backend.solver as sol
    import granite.backend.window as win
    import granite.estimator.landmark_creation as lc
    import granite.estimator.tracks as tr
    import granite.estimator.vo as vo
    import granite.optical_flow.frame_to_frame as ff

    # frontend (module globals as frame_to_frame calls them)
    wrap(ff, "track_points", "klt track_points")
    wrap(ff, "detect_new_points", "detection")
    wrap(ff, "build_pyramid", "pyramid")
    wrap(ff, "estimate_noise", "noise")
    # estimator
    W, V, DB = win.SlidingWindow, vo.MonocularVO, lm.LandmarkDatabase
    for owner, name, label in [
        (V, "estimate", "estimate (total)"), (V, "predict_tracks", "predict_tracks"),
        (V, "finish", "vo.finish"), (V, "window_landmarks", "export landmarks"),
        (V, "_scale_drift", "scale_drift"),
        (vo, "prediction_basis", "prediction_basis"),
        (W, "optimize", "window.optimize"), (W, "marginalize", "marginalize"),
        (W, "remove_outliers", "remove_outliers"), (W, "add_observations", "add_observations"),
        (W, "landmark_points", "win.landmark_points"), (W, "problem", "win.problem"),
        (lc.LandmarkTriangulator, "retriangulate_infinite", "retriangulate_infinite"),
        (lc.LandmarkTriangulator, "add_hosted_by", "add_hosted_by"),
        (DB, "pack", "db.pack"), (DB, "unpack_states", "db.unpack_states"),
        (DB, "inverse_distances", "db.inverse_distances"), (DB, "num_connected", "db.num_connected"),
        (lm, "pack_structure", "pack_structure"),
        (lin, "schur_reduce", "schur_reduce"), (lin, "linearize", "reproj.linearize"),
        (lin.WindowCost, "prior_terms", "prior_terms"), (lin.WindowCost, "cost", "cost.cost"),
        (sol, "optimize", "solver.optimize"), (sol, "solve_normal_equations", "solve_normal_eq"),
        (sol, "back_substitute", "back_substitute"),
        (pb.WindowProblem, "no_motion_pairs", "no_motion_pairs"),
        (pb.WindowProblem, "apply_step", "apply_step"),
        (sd, "_snapshot", "sd.snapshot"), (sd, "_system_of_snapshot", "sd.keyframe_system"),
        (sd, "scale_drift_of_system", "sd.of_system"),
        (tr.FrameTracks, "from_result", "FrameTracks.from_result"),
        (hs.WindowHessian, "negative_entropy", "negative_entropy"),
        (V, "_try_initialization", "map init (total)"),
        (vo, "init_candidates", "init.candidates"),
        (vo, "find_map_initialization", "init.two_view"),
    ]:
        wrap(owner, name, label)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset")
    parser.add_argument("--frames", type=int, help="first N frames only")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cprofile", help="write a cProfile of the first timed run here")
    parser.add_argument("--config", help="VO configuration TOML (default: the built-in defaults)")
    args = parser.parse_args()

    from granite.errors import GraniteError
    from granite.estimator.config import VoConfig
    from granite.estimator.pipeline import VoPipeline
    from granite.estimator.vo import MonocularVO
    from granite.io import open_dataset

    try:
        dataset = open_dataset(args.dataset)
        config = VoConfig.load(args.config) if args.config else VoConfig()
    except GraniteError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    n = len(dataset) if args.frames is None else min(args.frames, len(dataset))
    frames = list(dataset.frames(0, n))
    install_stage_timers()

    def run() -> np.ndarray:
        vo = MonocularVO(dataset.calibration.camera(), config)
        vo.export_landmarks = True  # as run_vo
        return np.array([out.T_w_c for _, out in VoPipeline(vo, False).run(frames)])

    ref = run()  # warms the numba cache
    for r in range(args.repeats):
        STAGE.clear()
        c0, w0 = time.process_time(), time.perf_counter()
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        if args.cprofile and r == 0:
            prof = cProfile.Profile()
            prof.enable()
            run()
            prof.disable()
            prof.dump_stats(args.cprofile)
            print(f"run 0: cProfile written to {args.cprofile} (not timed)")
            continue
        poses = run()
        cpu = 1e3 * (time.process_time() - c0) / n
        wall = 1e3 * (time.perf_counter() - w0) / n
        faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / n
        if not np.array_equal(poses, ref):
            print("error: the runs gave different poses", file=sys.stderr)
            return 1
        print(f"run {r}: CPU {cpu:.2f} ms/frame, wall {wall:.2f} ms/frame, {faults:.0f} page faults/frame, "
              f"load {os.getloadavg()[0]:.2f}")
        for label, seconds in sorted(STAGE.items()):
            print(f"  {label:28s} {1e3 * seconds / n:6.2f}")
        sys.stdout.flush()
    print(f"{n} frames; poses checksum {float(np.abs(ref).sum()).hex()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
