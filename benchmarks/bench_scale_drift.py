"""Validation of the scale-drift indicator Λ_scaledrift (paper Sec. V, Eq. 17, Fig. 4).

    python benchmarks/bench_scale_drift.py PATH [PATH ...] [--out DIR] [--delta 1] [--lag 1]
                                           [--bin 5] [--align-frames 100] [--plot] [--cost DATASET]
                                           [--exclude-scale-fix] [--config FILE]
    python benchmarks/bench_scale_drift.py --render spiral [--width 640 --height 480] --out DIR --plot

--render SCENARIO renders that scenario's whole flight with ``granite-sim render`` (at
``--width`` x ``--height``, default 640x480, the sensor model on) into
DIR/renders/<scenario>_<w>x<h> first (resumable: finished frames are kept) and adds it to the
PATHs (its run goes to DIR/<scenario>_<w>x<h>): the full 60 s ``spiral``
(1201 frames) takes about 20-45 min of CPU on 2 cores.

PATH is a run folder of `granite run` (diagnostics.csv with the scale_drift_indicator columns;
its dataset is read from summary.json) or a test-bench dataset folder, which is run first (in
process, default configuration, as `granite run`) into DIR/<name> (skipped when that run folder
exists; with --exclude-scale-fix into DIR/<name>_no_scale_fix, Λ leaving the scale fix of Eq. 9
out while it is in the window, as the reference does; with --config FILE in DIR/<name>_<stem of
FILE>, with that configuration, e.g. a keyframe-turnover option). For every run it prints,
for Eq. 17 (``Λ``) and the reference code's variant (``Λ_ref``) side by side:

* defined: the share of tracked frames (state tracking / reinit) with Λ defined, counted from
  the frame where the window holds 3 keyframes past the (last) initialisation ("kf>=3", i.e.
  one keyframe after the two of the map initialisation) and from the third keyframe taken after
  it ("kf+3");
* ρ(height): Spearman correlation of Λ with the true camera height (ground-truth z);
* ρ(bins): Spearman correlation, over ``--bin`` second bins, of the median Λ with the RMS true
  scale-drift rate (:func:`granite.evaluation.scale_drift_rate`: change of the log of the true
  relative scale error over ``--delta`` s of motion, per second, over ``--lag`` s);
* the RMS true relative scale error and the RMS RPE over ``--delta`` with the scale fixed by the
  Sim(3) alignment on the first ``--align-frames`` poses of each sub-map (paper Fig. 4: 100;
  :func:`granite.evaluation.rpe` with ``fixed_scales``), beside the scale-free RPE of Eq. 18-20;
* the median Λ and the RMS drift rate of the run; with several runs, Kendall's τ of the run
  ordering by median Λ against the ordering by RMS drift rate;
* the keyframe system over the run (does it follow the flight?): the number of keyframes, the
  longest time without a new keyframe (to the end of the run included), and the age of the oldest keyframe in the window (its
  maximum and median over the frames; from ``landmarks.npz``).
* how Λ (Eq. 17) moves (:func:`lambda_steps`): the share of consecutive frames over which it
  changes by less than 1e-4 (relative), and its median relative change on the frames that make
  a keyframe and on the frame after them. Λ reads keyframes only, so it moves at keyframe
  events (a keyframe taken or marginalised) and hardly in between.

--plot writes DIR/<name>_scale_drift.png (height, true relative scale error, Λ and Λ_ref,
drift rate, and the RPE per pair with the fixed scale and scale-free, over time, as the paper's
Fig. 4). --cost DATASET runs the VO in-process on the
dataset and times the indicator per frame (keyframe system: linearisation of the keyframe
observations and landmark elimination; chain: reparametrisation, Schur, eigen-solver).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.stats import kendalltau, spearmanr  # noqa: E402

from granite.estimator.diagnostics import read_diagnostics  # noqa: E402
from granite.evaluation import ate, relative_scale_error, rpe, scale_drift_rate  # noqa: E402
from granite.io import open_dataset  # noqa: E402
from granite.io.run_folder import read_estimate  # noqa: E402

TRACKED = ("tracking", "reinit")


def _run_folder(path: Path, out: Path, exclude_scale_fix: bool, config: Path | None = None) -> Path:
    """``path`` itself when it is a run folder, else the run of the dataset ``path`` in
    ``out`` (run in-process with the default configuration, or ``config``, when it does not
    exist yet)."""
    if (path / "diagnostics.csv").is_file():
        return path
    run = out / (path.name + ("_no_scale_fix" if exclude_scale_fix else "")
                 + (f"_{config.stem}" if config is not None else ""))
    if not (run / "diagnostics.csv").is_file():
        import granite.estimator.vo as vo_module
        from granite.backend import scale_drift_indicator
        from granite.cli.run_cmd import perform_run
        from granite.estimator.config import VoConfig

        print(f"running the VO on {path} -> {run}", flush=True)
        vo_module.scale_drift_indicator = functools.partial(
            scale_drift_indicator, include_scale_fix=not exclude_scale_fix)
        perform_run(open_dataset(path), VoConfig.load(config) if config is not None else VoConfig(), run,
                    progress=False)
        vo_module.scale_drift_indicator = scale_drift_indicator
    return run


def _eligible(diags) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the tracked frames once the window holds 3 keyframes past the last
    initialisation (the map initialisation makes 2), and from the 3rd keyframe after it."""
    a = np.zeros(len(diags), bool)
    b = np.zeros(len(diags), bool)
    since, prev = None, None
    for i, d in enumerate(diags):
        started = (d.state == "reinit" or (d.state == "tracking" and prev is not None and
                                           (prev.state in ("init", "lost") or prev.submap != d.submap)))
        if started:
            since = 0
        elif since is not None and d.keyframe:
            since += 1
        if d.state == "lost":
            since = None
        if d.state in TRACKED and since is not None:
            a[i] = since >= 1
            b[i] = since >= 3
        prev = d
    return a, b


def _spearman(x, y) -> float:
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        return float("nan")
    return float(spearmanr(x[ok], y[ok]).statistic)


def analyse(run: Path, delta: float, lag: float, bin_s: float, plot_dir: Path | None,
            min_motion: float = 0.1, align_frames: int | None = 100) -> dict:
    diags = read_diagnostics(run / "diagnostics.csv")
    summary = json.loads((run / "summary.json").read_text())
    dataset = open_dataset(summary["dataset"])
    gt = dataset.ground_truth
    traj, _ = read_estimate(run)
    t = np.array([d.timestamp for d in diags])
    lam = {k: np.array([np.nan if getattr(d, c) is None else getattr(d, c) for d in diags])
           for k, c in (("eq17", "scale_drift_indicator"), ("ref", "scale_drift_indicator_ref"))}
    height = np.interp(t, gt.timestamps, gt.positions[:, 2])
    scales = ate(traj, gt, align="sim3", align_frames=align_frames).scales
    series = relative_scale_error(traj, gt, delta, scales, min_motion=min_motion)
    rpe_fixed = rpe(traj, gt, delta, fixed_scales=scales)
    rpe_free = rpe(traj, gt, delta)
    rows = np.clip(np.searchsorted(traj.timestamps, series.timestamps - 1e-9), 0, len(traj) - 1)
    rate = scale_drift_rate(series, lag, traj.submap_ids()[rows])
    elig_a, elig_b = _eligible(diags)
    t0 = t[0]
    edges = np.arange(t0, t[-1] + bin_s, bin_s)
    out = {"run": str(run), "dataset": summary["dataset"], "frames": len(diags),
           "tracked": int(sum(d.state in TRACKED for d in diags)),
           "rms_drift_rate": float(np.sqrt(np.mean(rate.rates ** 2))) if rate.rates.size else None,
           "rms_scale_error": series.rms, "align_frames": align_frames,
           "rpe_fixed_scale_rmse": rpe_fixed.rmse, "rpe_rmse": rpe_free.rmse}
    for key, v in lam.items():
        defined = np.isfinite(v)
        med_lam, rms_rate = [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = defined & (t >= lo) & (t < hi)
            r = (rate.timestamps >= lo) & (rate.timestamps < hi)
            if m.sum() >= 3 and r.sum() >= 3:
                med_lam.append(float(np.median(v[m])))
                rms_rate.append(float(np.sqrt(np.mean(rate.rates[r] ** 2))))
        out[key] = {
            "defined_kf3": float(defined[elig_a].mean()) if elig_a.any() else None,
            "defined_kf_plus3": float(defined[elig_b].mean()) if elig_b.any() else None,
            "spearman_height": _spearman(v[defined], height[defined]),
            "spearman_bins": _spearman(med_lam, rms_rate), "bins": len(med_lam),
            "median": float(np.median(v[defined])) if defined.any() else None,
        }
    out["keyframe_system"] = keyframe_turnover(run, float(t[-1]))
    out["lambda_steps"] = lambda_steps(lam["eq17"], np.array([d.keyframe for d in diags]))
    if plot_dir is not None:
        _plot(plot_dir / f"{run.name}_scale_drift.png", t - t0, height, series, rate, lam, t0,
              (rpe_fixed, rpe_free), align_frames)
    return out


def keyframe_turnover(run: Path, t_end: float) -> dict:
    """Keyframes of a run folder, the longest time without a new keyframe [s] (the time from
    the last one to ``t_end``, the run's last frame, included) and the age of the oldest
    keyframe in the window per frame (max, median) [s]; the ages need landmarks.npz."""
    kf = np.loadtxt(run / "keyframes.csv", delimiter=",", skiprows=1, ndmin=2)
    out = {"keyframes": len(kf),
           "longest_keyframe_gap_s": float(np.diff(np.r_[kf[:, 0], t_end]).max()) if len(kf) else None,
           "oldest_keyframe_age_max_s": None, "oldest_keyframe_age_median_s": None}
    if (run / "landmarks.npz").is_file():
        z = np.load(run / "landmarks.npz")
        ts = dict(zip(z["frame_index"].tolist(), z["frame_timestamp"].tolist()))
        frames, ids = z["keyframe_frame"], z["keyframe_id"]
        order = np.argsort(frames, kind="stable")
        frames, ids = frames[order], ids[order]
        starts = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1]]) if len(frames) else np.zeros(0, int)
        ages = [ts[int(frames[a])] - min(ts[int(k)] for k in ids[a:b].tolist())
                for a, b in zip(starts, np.r_[starts[1:], len(frames)])]
        if ages:
            out["oldest_keyframe_age_max_s"] = float(np.max(ages))
            out["oldest_keyframe_age_median_s"] = float(np.median(ages))
    return out


def lambda_steps(lam: np.ndarray, keyframe: np.ndarray, still: float = 1e-4) -> dict:
    """How a per-frame Λ series moves (NaN where not defined; ``keyframe[k]``: frame k made a
    keyframe). Over the consecutive frame pairs (k - 1, k) with Λ defined at both, the relative
    change ``|Λ_k / Λ_{k-1} - 1|``: ``still_share``, the share of all such pairs below
    ``still``; ``keyframe_change_median``, the median signed change ``Λ_k / Λ_{k-1} - 1`` over
    the pairs whose frame k made a keyframe (``keyframe_events`` of them);
    ``after_keyframe_change_median`` the same for Λ of the frame after a keyframe frame
    against the frame before the keyframe frame (``Λ_{k+1} / Λ_{k-1} - 1``). None where there
    is no such pair."""
    lam = np.asarray(lam, dtype=float)
    keyframe = np.asarray(keyframe, dtype=bool)
    prev, cur = lam[:-1], lam[1:]
    pair = np.isfinite(prev) & np.isfinite(cur) & (prev > 0)
    change = np.full(cur.shape, np.nan)
    change[pair] = cur[pair] / prev[pair] - 1.0
    at_kf = pair & keyframe[1:]
    j = np.flatnonzero(at_kf[:-1] & np.isfinite(lam[2:]))  # frames j, j + 1 (keyframe), j + 2
    after_change = lam[j + 2] / lam[j] - 1.0
    return {
        "still_share": float(np.mean(np.abs(change[pair]) < still)) if pair.any() else None,
        "keyframe_events": int(at_kf.sum()),
        "keyframe_change_median": float(np.median(change[at_kf])) if at_kf.any() else None,
        "after_keyframe_change_median": float(np.median(after_change)) if after_change.size else None,
    }


def _plot(path: Path, t, height, series, rate, lam, t0, rpes, align_frames) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(10, 10), layout="constrained")
    ax = fig.subplots(5, 1, sharex=True)
    ax[0].plot(t, height, color="tab:orange")
    ax[0].set(ylabel="height [m]")
    ax[1].plot(series.timestamps - t0, 100 * series.errors, color="tab:blue")
    aligned = "all poses" if align_frames is None else f"the first {align_frames} poses"
    ax[1].set(ylabel="true rel. scale error [%]", title=f"scale of the Sim(3) alignment on {aligned}")
    ax[2].plot(t, lam["eq17"], color="tab:green", label="Λ (Eq. 17)")
    ax[2].plot(t, lam["ref"], color="tab:purple", label="Λ_ref (reference variant)")
    ax[2].set(ylabel="Λ", yscale="log")
    ax[2].legend(fontsize=8)
    ax[3].plot(rate.timestamps - t0, rate.rates, color="tab:gray", lw=0.8)
    ax[3].set(ylabel="scale-drift rate [1/s]")
    fixed, free = rpes
    ax[4].plot(fixed.timestamps - t0, fixed.errors, color="tab:red", lw=0.8, label="alignment's fixed scale")
    ax[4].plot(free.timestamps - t0, free.errors, color="tab:blue", lw=0.8, label="scale-free (Eq. 18-20)")
    ax[4].set(ylabel=f"RPE over {fixed.delta:g} s [m]", xlabel="time [s]")
    ax[4].legend(fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
    FigureCanvasAgg(fig).print_png(str(path))
    print("wrote", path)


def cost(dataset_path: str) -> dict:
    """Per-frame CPU time (``time.thread_time``: the machine may be shared; OpenBLAS runs
    single-threaded) of the indicator inside the VO (in-process sequential run of the dataset):
    the whole computation as the VO makes it (the window's snapshot and the computation on
    it, :func:`granite.backend.scale_drift_task`), and separately the keyframe system
    (linearisation of the keyframe observations, landmark elimination) and the chain part
    (reparametrisation, Schur complements, eigen-solver). Each is timed 3 times on the frame's
    window: the first whole computation ("cold") runs, as in the VO, right after the
    optimisation has evicted its data from the caches; the means are over the 3."""
    import granite.estimator.vo as vo_module
    from granite.backend import keyframe_system, scale_drift_of_system, scale_drift_task
    from granite.estimator.config import VoConfig
    from granite.estimator.runner import run_vo

    samples = []
    reps = 3

    def timed_task(window, include_scale_fix=True, workspaces=None):
        n = len(window.keyframe_ids)
        if n < 3:
            return scale_drift_task(window, include_scale_fix, workspaces)
        whole = []
        for _ in range(reps):
            a = time.thread_time()
            res = scale_drift_task(window, include_scale_fix, workspaces)()
            whole.append(time.thread_time() - a)
        b = time.thread_time()
        for _ in range(reps):
            system = keyframe_system(window, include_scale_fix)
        c = time.thread_time()
        for _ in range(reps):
            scale_drift_of_system(system)
        d = time.thread_time()
        samples.append((n, 1e3 * whole[0], 1e3 * float(np.mean(whole)), 1e3 * (c - b) / reps,
                        1e3 * (d - c) / reps))
        return lambda: res

    vo_module.scale_drift_task = timed_task
    try:
        run_vo(open_dataset(dataset_path), VoConfig(), progress=False, concurrent=False)
    finally:  # the VO module is shared with whatever runs after (e.g. the tests)
        vo_module.scale_drift_task = scale_drift_task
    if not samples:
        raise SystemExit(f"error: the window of {dataset_path} never held 3 keyframes")
    arr = np.array(samples)
    total = arr[:, 2]
    return {"frames": len(arr), "max_keyframes": int(arr[:, 0].max()),
            "cold_ms_mean": float(arr[:, 1].mean()),
            "total_ms": {"mean": float(total.mean()), "median": float(np.median(total)),
                         "p95": float(np.percentile(total, 95)), "max": float(total.max())},
            "keyframe_system_ms_mean": float(arr[:, 3].mean()),
            "chain_ms_mean": float(arr[:, 4].mean()), "chain_ms_max": float(arr[:, 4].max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog="See the module docstring "
                                 "(the file's header) for what every figure means.")
    ap.add_argument("paths", nargs="*", type=Path, metavar="PATH",
                    help="run folders of `granite run`, or test-bench dataset folders (run here first)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_scale_drift"),
                    help="folder of the runs made here, the renders and the plots (default %(default)s)")
    ap.add_argument("--render", metavar="SCENARIO", action="append", default=[],
                    help="render this scenario's whole flight into OUT/renders/<scenario>_<w>x<h> first "
                         "(resumable) and add it to the PATHs; repeatable")
    ap.add_argument("--width", type=int, default=640, help="--render image width (default 640)")
    ap.add_argument("--height", type=int, default=480, help="--render image height (default 480)")
    ap.add_argument("--delta", type=float, default=1.0,
                    help="time over which the true relative scale error and the RPE are taken [s] (default 1)")
    ap.add_argument("--lag", type=float, default=1.0,
                    help="time over which the drift rate differentiates the log scale [s] (default 1)")
    ap.add_argument("--bin", type=float, default=5.0,
                    help="bin length of the binned Spearman correlation ρ(bins) [s] (default 5)")
    ap.add_argument("--align-frames", type=int, default=100,
                    help="Sim(3) alignment on the first N poses of each sub-map for the scale error "
                         "and the fixed-scale RPE (paper Fig. 4: 100; 0: all poses)")
    ap.add_argument("--min-motion", type=float, default=0.1,
                    help="true motion over --delta below which a pair gives no scale (m)")
    ap.add_argument("--plot", action="store_true", help="write OUT/<run>_scale_drift.png (Fig. 4 style)")
    ap.add_argument("--cost", default=None, metavar="DATASET",
                    help="time the indicator per frame on this dataset (sequential VO in process)")
    ap.add_argument("--exclude-scale-fix", action="store_true",
                    help="datasets run here leave the scale fix out of Λ while it is in the window "
                         "(the reference's choice; runs go to DIR/<name>_no_scale_fix)")
    ap.add_argument("--config", type=Path, default=None,
                    help="configuration for the datasets run here (runs go to DIR/<name>_<stem>)")
    args = ap.parse_args(argv)
    if args.align_frames != 0 and args.align_frames < 3:
        print("error: --align-frames must be 0 (all poses) or at least 3", file=sys.stderr)
        return 2
    if args.config is not None:
        from granite.errors import ConfigError
        from granite.estimator.config import VoConfig
        try:
            VoConfig.load(args.config)
        except ConfigError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
    for scenario in args.render:
        dataset = args.out / "renders" / f"{Path(scenario).stem}_{args.width}x{args.height}"
        command = [sys.executable, "-m", "simulation.cli", "render", scenario, "--out", str(dataset),
                   "--width", str(args.width), "--height", str(args.height)]
        print("$ granite-sim", " ".join(command[3:]), flush=True)
        if subprocess.run(command).returncode != 0:
            print(f"error: rendering {scenario} failed (see above)", file=sys.stderr)
            return 2
        args.paths.append(dataset)
    args.out.mkdir(parents=True, exist_ok=True)
    results = []
    for path in args.paths:
        results.append(analyse(_run_folder(path, args.out, args.exclude_scale_fix, args.config), args.delta,
                               args.lag, args.bin, args.out if args.plot else None, args.min_motion,
                               args.align_frames or None))
    fmt = lambda x, p=3: "  n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{p}f}"  # noqa: E731
    if results:
        print(f"\nΔ = {args.delta:g} s (true motion >= {args.min_motion:g} m), lag = {args.lag:g} s, "
              f"bins of {args.bin:g} s")
        print(f"{'run':34s} {'variant':7s} {'def kf>=3':>9s} {'def kf+3':>9s} {'ρ(height)':>9s} "
              f"{'ρ(bins)':>8s} {'bins':>4s} {'median Λ':>9s} {'RMS rate':>9s}")
        for r in results:
            for key, label in (("eq17", "Eq. 17"), ("ref", "ref")):
                v = r[key]
                print(f"{Path(r['run']).name[:34]:34s} {label:7s} {fmt(v['defined_kf3']):>9s} "
                      f"{fmt(v['defined_kf_plus3']):>9s} {fmt(v['spearman_height']):>9s} "
                      f"{fmt(v['spearman_bins']):>8s} {v['bins']:4d} {fmt(v['median'], 4):>9s} "
                      f"{fmt(r['rms_drift_rate'], 4):>9s}")
        print(f"\n{'run':34s} {'keyframes':>9s} {'longest gap [s]':>15s} {'oldest kf age max / median [s]':>31s}")
        for r in results:
            k = r["keyframe_system"]
            ages = f"{fmt(k['oldest_keyframe_age_max_s'], 1)} / {fmt(k['oldest_keyframe_age_median_s'], 1)}"
            print(f"{Path(r['run']).name[:34]:34s} {k['keyframes']:9d} {fmt(k['longest_keyframe_gap_s'], 1):>15s} "
                  f"{ages:>31s}")
        print(f"\n{'run':34s} {'Λ still (< 1e-4)':>16s} {'keyframe frames':>15s} {'Λ change at / after them (median)':>34s}")
        for r in results:
            st = r["lambda_steps"]
            pct = lambda x: "  n/a" if x is None else f"{100 * x:+.1f} %"  # noqa: E731
            share = "  n/a" if st["still_share"] is None else f"{100 * st['still_share']:.1f} %"
            print(f"{Path(r['run']).name[:34]:34s} {share:>16s} {st['keyframe_events']:15d} "
                  f"{pct(st['keyframe_change_median']) + ' / ' + pct(st['after_keyframe_change_median']):>34s}")
        aligned = "all poses" if args.align_frames == 0 else f"first {args.align_frames} poses"
        print(f"\n{'run':34s} {'RMS scale error':>15s} {'RMS RPE fixed scale':>19s} {'RMS RPE Eq. 18-20':>17s}"
              f"   (Sim(3) on the {aligned}; Δ = {args.delta:g} s)")
        for r in results:
            print(f"{Path(r['run']).name[:34]:34s} {fmt(r['rms_scale_error'], 4):>15s} "
                  f"{fmt(r['rpe_fixed_scale_rmse'], 4):>19s} {fmt(r['rpe_rmse'], 4):>17s}")
    if len(results) >= 2:
        for key, label in (("eq17", "Eq. 17"), ("ref", "reference variant")):
            pairs = [(r[key]["median"], r["rms_drift_rate"]) for r in results
                     if r[key]["median"] is not None and r["rms_drift_rate"] is not None]
            tau = kendalltau(*zip(*pairs)).statistic if len(pairs) >= 2 else float("nan")
            print(f"Kendall τ (median Λ vs RMS drift rate, {len(pairs)} runs), {label}: {tau:.3f}")
    if args.cost:
        import _host  # benchmarks/_host.py

        probe = _host.speed_probe()
        c = cost(args.cost)
        c.update(probe)
        print(f"\nCPU time on {args.cost}: {c['frames']} frames with >= 3 keyframes (at most "
              f"{c['max_keyframes']}): cold (first call, as in the VO) mean {c['cold_ms_mean']:.2f} ms; "
              f"total per frame mean {c['total_ms']['mean']:.2f} ms, median "
              f"{c['total_ms']['median']:.2f}, p95 {c['total_ms']['p95']:.2f}, max {c['total_ms']['max']:.2f}; "
              f"fast path: keyframe system {c['keyframe_system_ms_mean']:.2f} ms, chain + Schur + eigen "
              f"{c['chain_ms_mean']:.2f} ms (max {c['chain_ms_max']:.2f}); {_host.probe_text(probe)}")
        results.append({"cost": c})
    (args.out / "bench_scale_drift.json").write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
