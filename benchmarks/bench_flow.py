"""Benchmark of the optical-flow frontend against OpenCV's pyramidal Lucas-Kanade.

    python benchmarks/bench_flow.py [DATASET ...] [--frames N] [--resize WxH] [--noise SPEC]
                                    [--set KEY=VALUE] [--repeat N] [--diagnose] [--ablation]

Without DATASET (or with the word ``synthetic`` among them): a synthetic 640x480 sequence (a
textured plane seen through a moving, rotating, zooming window, with frame drops of 4 frames
every 15), ground truth = the exact image motion. With one or more DATASET folders (any layout granite.io reads, e.g. the
test-bench's ``assets/sequences/*`` or real sequences): their frames at native size (or
``--resize``), ground-truth flow from the test-bench's depth maps and poses where they exist
(``mav0/depth0``); real sequences without depth get no ground-truth columns.

Our frontend runs as ``granite track`` does (unguided, every frame). Per dataset and per
creation level c of the tracks, one markdown table:

- survival: per-step survival, the median over frame steps k of the share of the level-c
  tracks of frame k still tracked in frame k+1 (as ``shared/tools/track_survival.py``);
- OpenCV on the same points: ``calcOpticalFlowPyrLK`` (21x21 window, 3 levels unless
  ``--lk-levels``) applied to exactly our tracks of frame k, kept when tracked forward and
  back to within the same forward-backward limit as the reference (``fb_threshold_sq`` of the
  reference, 0.03 creation-level px², i.e. 0.17 px at level 0);
- track length: median number of frames a track of that level lives; for OpenCV a chain
  tracker (LK + the same forward-backward limit + our detector on the same grid) run over
  the same frames;
- ground truth (where depth exists): error of the tracks that survived a step against the
  ground-truth flow, level-0 pixels: median and share beyond 2 px, ours and OpenCV's; and
  "in view", the per-step median share of the tracks whose ground-truth position in the next
  frame is at least 3 px inside the image (with valid depth): no frame-to-frame tracker can
  keep more.

A second table gives the time per frame of our frontend (one core: numba kernels are
single-threaded, NUMBA_NUM_THREADS=1, cv2.setNumThreads(1); median over frames, from the run
of ``--repeat`` with the lowest median CPU time): wall-clock per stage and in total, and the
thread's CPU time per frame, which other jobs on a shared machine disturb far less; beside
OpenCV's forward + backward LK on the same points (wall clock). ``--diagnose``
adds forward-backward distance distributions per level (without any limit) for both trackers.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from granite.optical_flow import FrameRejectedWarning, FrameToFrameOpticalFlow, OpticalFlowConfig  # noqa: E402
from granite.optical_flow.detection import detect_new_points  # noqa: E402
from granite.optical_flow.pyramid import build_pyramid  # noqa: E402
from granite.optical_flow.synthetic import add_noise, apply_affine, similarity, textured_image, warp  # noqa: E402

SYNTHETIC_SIZE = (640, 480)
#: The reference's forward-backward limit (squared, creation-level pixels), used for OpenCV.
REFERENCE_FB_SQ = OpticalFlowConfig().fb_threshold_sq


@dataclass
class Sequence:
    """Frames plus a ground-truth mapping ``gt(i, j, uv_i) -> (uv_j, valid)`` or None."""

    name: str
    description: str
    timestamps: np.ndarray
    images: list[np.ndarray]
    gt: object = None
    notes: list[str] = field(default_factory=list)


def synthetic_sequence(n_frames: int) -> Sequence:
    big = textured_image(1400, 1800, seed=3)
    affines, stamps, k = [], [], 0
    for i in range(n_frames):
        if i and i % 15 == 0:
            k += 4  # frame drop: 4 frames missing
        a = similarity(-6.0 * k, -3.0 * k, np.radians(0.3 * k), 1.0 + 0.002 * k, (900, 700))
        a[:, 2] -= (580, 460)
        affines.append(a)
        stamps.append(0.05 * k)
        k += 1
    images = [warp(big, a, SYNTHETIC_SIZE) for a in affines]

    def gt(i: int, j: int, uv: np.ndarray):
        back = apply_affine(cv2.invertAffineTransform(affines[i]), uv)
        return apply_affine(affines[j], back), np.ones(len(uv), bool)

    return Sequence(
        "synthetic",
        f"synthetic 640x480 texture, {n_frames} frames, 6 px + 0.3 deg + 0.2 % zoom per "
        "frame, 4-frame drops every 15 frames; ground truth: exact image motion",
        np.asarray(stamps), images, gt,
    )


def parse_noise(spec: str | None) -> tuple[float, float] | None:
    """``gauss:SIGMA`` or ``shot:READ:GAIN`` (variance READ² + GAIN * I) -> (read, gain)."""
    if not spec:
        return None
    kind, *values = spec.split(":")
    try:
        numbers = [float(v) for v in values]
    except ValueError:
        numbers = []
    if kind == "gauss" and len(numbers) == 1:
        return numbers[0], 0.0
    if kind == "shot" and len(numbers) == 2:
        return numbers[0], numbers[1]
    raise SystemExit(f"--noise: expected gauss:SIGMA or shot:READ:GAIN, got {spec!r}")


def dataset_sequence(path: Path, n_frames: int | None, resize: tuple[int, int] | None = None,
                     noise: tuple[float, float] | None = None, seed: int = 0) -> Sequence:
    from granite.io import open_dataset

    ds = open_dataset(path)
    frames = [f for f in ds.frames(0, n_frames) if f.image is not None]
    if not frames:
        raise SystemExit(f"no readable frames in {path}")
    h, w = frames[0].image.shape
    notes = []
    images = [f.image for f in frames]
    if noise is not None:
        images = [add_noise(im, noise[0], noise[1], (seed, f.index)) for im, f in zip(images, frames)]
        notes.append(f"seeded noise: read {noise[0]} DN, shot gain {noise[1]} DN (seed {seed})")
    if resize is not None and (w, h) != resize:
        sx, sy = resize[0] / w, resize[1] / h
        images = [cv2.resize(im, resize, interpolation=cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR)
                  for im in images]
        notes.append(f"frames resized from {w}x{h} to {resize[0]}x{resize[1]} (x{sx:.3f}, y{sy:.3f})")
    else:
        sx = sy = 1.0
    gt = None
    depth_loader = _depth_loader(ds)
    if depth_loader is not None and ds.ground_truth is not None and ds.calibration is not None:
        from granite.geometry import interpolate_poses
        from granite.optical_flow.gt_flow import ground_truth_flow

        camera = ds.calibration.camera()
        stamps = np.array([f.timestamp for f in frames])
        poses = interpolate_poses(ds.ground_truth.timestamps, ds.ground_truth.poses, stamps)
        scale = np.array([sx, sy])

        def gt(i: int, j: int, uv: np.ndarray):
            native_uv = (uv + 0.5) / scale - 0.5
            uv_j, ok = ground_truth_flow(native_uv, depth_loader(frames[i].index), poses[i], poses[j], camera)
            return (uv_j + 0.5) * scale - 0.5, ok

        notes.append("ground truth: flow from the depth maps and ground-truth poses")
    else:
        notes.append("no ground-truth flow (needs depth maps, poses and calibration)")
    name = path.resolve().name
    if path.resolve().parent.name not in ("sequences", "realdata"):
        name = f"{path.resolve().parent.name}/{name}"
    if noise is not None:
        name += f" +noise({noise[0]:g},{noise[1]:g})"
    return Sequence(name, f"{path} ({len(images)} frames)", np.array([f.timestamp for f in frames]),
                    images, gt, notes)


def _depth_loader(ds):
    """Depth of dataset frame i (planar z, metres) from the test-bench layout
    (``mav0/depth0/data/<ns>.npy|.png``, see simulation/depth.py), or None."""
    folder = Path(ds.root) / "mav0" / "depth0" / "data"
    if ds.timestamps_ns is None or not folder.is_dir():
        return None
    from simulation.depth import read_depth

    def load(i: int) -> np.ndarray:
        ns = int(ds.timestamps_ns[i])
        for ext in (".npy", ".png"):
            if (folder / f"{ns}{ext}").is_file():
                return read_depth(folder / f"{ns}{ext}")
        raise FileNotFoundError(f"no depth map for frame {i} ({ns} ns) in {folder}")

    return load


def to_u8(img: np.ndarray) -> np.ndarray:
    return img if img.dtype == np.uint8 else cv2.convertScaleAbs(img, alpha=255.0 / 65535.0)


# ---------------------------------------------------------------------------------------------
# Runs


def run_ours(seq: Sequence, config: OpticalFlowConfig) -> tuple[list, list]:
    """Our frontend over every frame: (frame index, result) of the accepted frames and the
    per-frame timings (ms dicts)."""
    warm = FrameToFrameOpticalFlow(config)  # numba compilation / cache load outside the timing
    warm.process(0.0, seq.images[0])
    warm.process(0.1, seq.images[min(1, len(seq.images) - 1)])
    flow = FrameToFrameOpticalFlow(config)
    out, timing = [], []
    for i, img in enumerate(seq.images):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FrameRejectedWarning)
            c0 = time.thread_time()
            r = flow.process(float(seq.timestamps[i]), img)
            cpu = 1e3 * (time.thread_time() - c0)
        if r.rejected:
            continue
        if out:
            timing.append({**r.timing, "cpu": cpu})
        out.append((i, r))
    return out, timing


def lk_params(levels: int, window: int) -> dict:
    return dict(winSize=(window, window), maxLevel=levels - 1,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))


def lk_track(a: np.ndarray, b: np.ndarray, p0: np.ndarray, levels_c: np.ndarray, params: dict,
             fb_sq: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """OpenCV LK forward a -> b and back; (p1 (N, 2), kept (N,), fb distance in creation-level
    px (N,), ms). Kept: both directions found, inside image b, forward-backward squared
    distance in creation-level pixels below ``fb_sq``."""
    if len(p0) == 0:
        return np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0), 0.0
    pts = p0.astype(np.float32).reshape(-1, 1, 2)
    t0 = time.perf_counter()
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, pts, None, **params)
    pb, stb, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, **params)
    ms = 1e3 * (time.perf_counter() - t0)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    fb = np.linalg.norm(pb.reshape(-1, 2) - p0, axis=1) / 2.0 ** levels_c
    h, w = b.shape
    inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    ok = (st.ravel() == 1) & (stb.ravel() == 1) & inside
    fb[~ok] = np.inf
    return p1, ok & (fb * fb < fb_sq), fb, ms


def run_lk_chain(seq: Sequence, frames: list[int], config: OpticalFlowConfig, params: dict,
                 fb_sq: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """OpenCV LK as a frontend: tracks of the previous frame by LK with the forward-backward
    limit, new points from our detector (same grid, levels, FAST thresholds). Per frame:
    (ids, levels)."""
    out = []
    pts, lv, ids, next_id, prev = np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0, np.int64), 0, None
    for i in frames:
        img = to_u8(seq.images[i])
        if prev is not None and len(pts):
            p1, kept, _, _ = lk_track(prev, img, pts, lv, params, fb_sq)
            pts, lv, ids = p1[kept], lv[kept], ids[kept]
        pyr = build_pyramid(seq.images[i], config.levels, config.presmooth_sigma)
        new_p, new_l = detect_new_points(pyr, config, pts, lv)
        pts = np.concatenate([pts, new_p])
        lv = np.concatenate([lv, new_l])
        ids = np.concatenate([ids, np.arange(next_id, next_id + len(new_p))])
        next_id += len(new_p)
        out.append((ids.copy(), lv.copy()))
        prev = img
    return out


# ---------------------------------------------------------------------------------------------
# Statistics


def survival_and_length(per_frame: list[tuple[np.ndarray, np.ndarray]], level: int) -> tuple[float, float, float]:
    """(per-step survival, median track length [frames], tracks per frame) of the tracks
    created on ``level`` (None: all), from per-frame (ids, levels)."""
    sets = [ids[lv == level] if level is not None else ids for ids, lv in per_frame]
    steps = [np.isin(a, b).mean() for a, b in zip(sets[:-1], sets[1:]) if len(a)]
    everything = np.concatenate(sets) if sets else np.zeros(0, np.int64)
    _, counts = np.unique(everything, return_counts=True)
    return (float(np.median(steps)) if steps else float("nan"),
            float(np.median(counts)) if len(counts) else float("nan"),
            float(np.mean([len(s) for s in sets])) if sets else 0.0)


@dataclass
class DatasetStats:
    seq: Sequence
    config: OpticalFlowConfig
    ours: list  # (frame, OpticalFlowResult)
    timing: list
    lk_kept: list = field(default_factory=list)  # per step: (levels (N,), kept (N,))
    lk_ms: list = field(default_factory=list)
    err_ours: list = field(default_factory=list)  # per step: (levels, error) of surviving tracks
    err_lk: list = field(default_factory=list)
    fb_ours: list = field(default_factory=list)  # --diagnose: (levels, fb distance, gt error)
    fb_lk: list = field(default_factory=list)
    lk_chain: list = field(default_factory=list)
    in_view: list = field(default_factory=list)  # per step: (levels, in view (N,)) where GT exists


def analyse(seq: Sequence, config: OpticalFlowConfig, lk_levels: int, lk_window: int,
            diagnose: bool, repeat: int) -> DatasetStats:
    ours, timing = run_ours(seq, config)
    for _ in range(repeat - 1):
        _, t = run_ours(seq, config)
        if np.median([x["cpu"] for x in t]) < np.median([x["cpu"] for x in timing]):
            timing = t
    stats = DatasetStats(seq, config, ours, timing)
    params = lk_params(lk_levels, lk_window)
    for (i, a), (j, b) in zip(ours[:-1], ours[1:]):
        if not len(a):
            continue
        _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
        img_a, img_b = to_u8(seq.images[i]), to_u8(seq.images[j])
        p1, kept, fb_lk, ms = lk_track(img_a, img_b, a.positions, a.levels, params, REFERENCE_FB_SQ)
        stats.lk_kept.append((a.levels, kept))
        stats.lk_ms.append(ms)
        if seq.gt is not None:
            uv_gt, ok = seq.gt(i, j, a.positions)
            h, w = img_b.shape
            inside = ok & (uv_gt[:, 0] >= 3) & (uv_gt[:, 1] >= 3) & (uv_gt[:, 0] <= w - 4) & (uv_gt[:, 1] <= h - 4)
            stats.in_view.append((a.levels[ok], inside[ok]))
            e = np.linalg.norm(b.positions[ib] - uv_gt[ia], axis=1)
            stats.err_ours.append((a.levels[ia][ok[ia]], e[ok[ia]]))
            e_lk = np.linalg.norm(p1 - uv_gt, axis=1)
            stats.err_lk.append((a.levels[kept & ok], e_lk[kept & ok]))
        if diagnose:
            from granite.optical_flow.diagnostics import forward_backward

            pa = build_pyramid(seq.images[i], config.levels, config.presmooth_sigma)
            pb = build_pyramid(seq.images[j], config.levels, config.presmooth_sigma)
            q1, fb = forward_backward(pa, pb, a.positions, a.levels, config)
            e_q = np.full(len(a), np.nan)
            e_l = np.full(len(a), np.nan)
            if seq.gt is not None:
                e_q[ok] = np.linalg.norm(q1 - uv_gt, axis=1)[ok]
                e_l[ok] = np.linalg.norm(p1 - uv_gt, axis=1)[ok]
            stats.fb_ours.append((a.levels, fb, e_q))
            stats.fb_lk.append((a.levels, fb_lk, e_l))
    frames = [i for i, _ in ours]
    stats.lk_chain = run_lk_chain(seq, frames, config, params, REFERENCE_FB_SQ)
    return stats


def _cat(items: list, level) -> list[np.ndarray]:
    if not items:
        return []
    cols = list(zip(*items))
    lv = np.concatenate(cols[0])
    sel = np.ones(len(lv), bool) if level is None else lv == level
    return [np.concatenate(c)[sel] for c in cols[1:]]


def _err(items: list, level) -> str:
    cols = _cat(items, level)
    if not cols or not len(cols[0]):
        return "- | -"
    e = cols[0]
    return f"{np.median(e):.3f} | {100 * np.mean(e > 2.0):.2f}"


def _fmt(x: float, digits: int = 2) -> str:
    return "-" if not np.isfinite(x) else f"{x:.{digits}f}"


def table(all_stats: list[DatasetStats]) -> str:
    head = ("| dataset | level | tracks/frame | survival ours | survival OpenCV (same points) "
            "| survival OpenCV chain | track length ours | track length OpenCV chain "
            "| GT err ours median px | ours > 2 px % | GT err OpenCV median px | OpenCV > 2 px % "
            "| in view (GT) |")
    lines = [head, "|" + " --- |" * 13]
    for s in all_stats:
        per_frame = [(r.ids, r.levels) for _, r in s.ours]
        present = sorted(set(np.concatenate([lv for _, lv in per_frame]).tolist())) if per_frame else []
        for level in present + [None]:
            surv, length, count = survival_and_length(per_frame, level)
            steps = [kept[lv == level] if level is not None else kept for lv, kept in s.lk_kept]
            lk_surv = np.median([k.mean() for k in steps if len(k)]) if any(len(k) for k in steps) else np.nan
            c_surv, c_len, _ = survival_and_length(s.lk_chain, level)
            gt_ours = _err(s.err_ours, level) if s.seq.gt is not None else "- | -"
            gt_lk = _err(s.err_lk, level) if s.seq.gt is not None else "- | -"
            view = [v[lv == level] if level is not None else v for lv, v in s.in_view]
            view = _fmt(np.median([v.mean() for v in view if len(v)])) if any(len(v) for v in view) else "-"
            lines.append(
                f"| {s.seq.name} | {'all' if level is None else level} | {count:.0f} | {_fmt(surv)} | "
                f"{_fmt(lk_surv)} | {_fmt(c_surv)} | {_fmt(length, 0)} | {_fmt(c_len, 0)} | {gt_ours} | {gt_lk} | {view} |"
            )
    return "\n".join(lines)


def timing_table(all_stats: list[DatasetStats]) -> str:
    lines = ["| dataset | size | points/frame | ours ms/frame: pyramid | tracking | detection | total "
             "| ours CPU ms/frame | us/point tracked | OpenCV LK fwd+bwd ms (same points) |", "|" + " --- |" * 10]
    for s in all_stats:
        med = {k: float(np.median([t[k] for t in s.timing])) for k in ("pyramid", "tracking", "detection", "total", "cpu")}
        h, w = s.seq.images[0].shape
        pts = float(np.median([len(r) for _, r in s.ours]))
        tracked = float(np.median([int((~r.new).sum()) for _, r in s.ours[1:]])) if len(s.ours) > 1 else 0.0
        lines.append(
            f"| {s.seq.name} | {w}x{h} | {pts:.0f} | {med['pyramid']:.2f} | {med['tracking']:.2f} | "
            f"{med['detection']:.2f} | {med['total']:.2f} | {med['cpu']:.2f} | {1e3 * med['tracking'] / max(tracked, 1):.1f} | "
            f"{np.median(s.lk_ms):.2f} |"
        )
    return "\n".join(lines)


def diagnosis_table(all_stats: list[DatasetStats]) -> str:
    bins = [0.0, np.sqrt(REFERENCE_FB_SQ), 0.5, 2.0, np.inf]
    lines = ["| dataset | level | tracker | FB p50 | p90 | < 0.17 % | 0.17-0.5 % | 0.5-2 % | > 2 % | lost % "
             "| fwd GT err p50 (no FB limit) | fwd > 2 px % |", "|" + " --- |" * 12]
    for s in all_stats:
        if not s.fb_ours:
            continue
        present = sorted(set(np.concatenate([x[0] for x in s.fb_ours]).tolist()))
        for level in present:
            for name, items in (("ours", s.fb_ours), ("OpenCV", s.fb_lk)):
                fb, e = _cat(items, level)
                fin = fb[np.isfinite(fb)]
                hist = [100 * np.mean((fb >= a) & (fb < b)) for a, b in zip(bins[:-1], bins[1:])]
                ef = e[np.isfinite(e)]
                gt = f"{np.median(ef):.3f} | {100 * np.mean(ef > 2):.1f}" if len(ef) else "- | -"
                lines.append(
                    f"| {s.seq.name} | {level} | {name} | {_fmt(np.median(fin), 3) if len(fin) else '-'} | "
                    f"{_fmt(np.percentile(fin, 90), 3) if len(fin) else '-'} | "
                    + " | ".join(f"{h:.1f}" for h in hist)
                    + f" | {100 * np.mean(~np.isfinite(fb)):.1f} | {gt} |"
                )
    return "\n".join(lines)


def parse_overrides(items: list[str]) -> dict:
    overrides = {}
    for item in items:
        key, _, value = item.partition("=")
        v = value.strip()
        if v.lower() in ("true", "false"):
            overrides[key.strip()] = v.lower() == "true"
            continue
        try:
            overrides[key.strip()] = float(v) if any(c in v for c in ".eE") else int(v)
        except ValueError:  # a string value, e.g. pattern=pattern52
            overrides[key.strip()] = v.strip("\"'")
    return overrides


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("datasets", nargs="*", type=Path, metavar="DATASET")
    parser.add_argument("--frames", type=int, help="use the first N frames (default all; synthetic: 60)")
    parser.add_argument("--resize", metavar="WxH", help="resize dataset frames, e.g. 640x480 (default native)")
    parser.add_argument("--native", action="store_true", help=argparse.SUPPRESS)  # old flag; native is the default
    parser.add_argument("--noise", metavar="SPEC",
                        help="add seeded noise to dataset frames: gauss:SIGMA or shot:READ:GAIN (var = READ² + GAIN*I)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument("--lk-levels", type=int, default=3, help="OpenCV LK pyramid levels (default 3)")
    parser.add_argument("--lk-window", type=int, default=21, help="OpenCV LK window (default 21)")
    parser.add_argument("--repeat", type=int, default=1, help="runs of our frontend for the timing (best median)")
    parser.add_argument("--diagnose", action="store_true",
                        help="forward-backward distance distributions per level (no limit), both trackers")
    parser.add_argument("--ablation", action="store_true",
                        help="also run the ablation † (corners on the finest level only)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override an OpticalFlowConfig field (repeatable), e.g. presmooth_sigma=0.7")
    args = parser.parse_args(argv)
    overrides = parse_overrides(args.set)
    resize = None
    if args.resize:
        try:
            resize = tuple(int(v) for v in args.resize.lower().split("x"))
            assert len(resize) == 2
        except (ValueError, AssertionError):
            raise SystemExit(f"--resize: expected WxH, got {args.resize!r}") from None
    noise = parse_noise(args.noise)
    cv2.setNumThreads(1)
    base = OpticalFlowConfig.from_dict(overrides)
    configs = [("", base)]
    if args.ablation:
        configs.append((" †", OpticalFlowConfig.from_dict({**base.to_dict(), "detect_all_levels": False})))
    print("threads: one core (numba kernels single-threaded, NUMBA_NUM_THREADS=1, cv2.setNumThreads(1))")
    print(f"OpenCV: calcOpticalFlowPyrLK {args.lk_window}x{args.lk_window}, {args.lk_levels} levels, forward-backward "
          f"limit {REFERENCE_FB_SQ} creation-level px² (the reference's)")
    if overrides:
        print(f"config overrides: {overrides}")
    all_stats = []
    paths = args.datasets or [None]
    for path in paths:
        seq = (dataset_sequence(path, args.frames, resize, noise, args.seed)
               if path is not None and str(path) != "synthetic" else synthetic_sequence(args.frames or 60))
        h, w = seq.images[0].shape
        print(f"input: {seq.description}; frames {w}x{h} {seq.images[0].dtype}")
        for note in seq.notes:
            print(f"  {note}")
        for suffix, config in configs:
            s = analyse(seq, config, args.lk_levels, args.lk_window, args.diagnose, max(1, args.repeat))
            if suffix:
                s.seq = Sequence(seq.name + suffix, seq.description, seq.timestamps, seq.images, seq.gt)
            all_stats.append(s)
    print()
    print(table(all_stats))
    print()
    print(timing_table(all_stats))
    if args.diagnose:
        print()
        print(diagnosis_table(all_stats))
    return 0


if __name__ == "__main__":
    sys.exit(main())
