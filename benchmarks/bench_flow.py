"""Benchmark of the optical-flow frontend against OpenCV's pyramidal Lucas-Kanade.

    python benchmarks/bench_flow.py [DATASET] [--frames N] [--native] [--ablation] [--set KEY=VALUE]

Without DATASET: a synthetic 640x480 sequence (a textured plane seen through a moving,
rotating, zooming window, with frame drops of 4 frames every 15), ground truth = the exact
image motion. With DATASET (any layout granite.io reads): its frames, resized to 640x480
unless --native; ground-truth flow from the test-bench's depth maps and poses when present.

Prints per-frame milliseconds of our pyramid / detection / tracking (median over frames, one
core: numba kernels are single-threaded, NUMBA_NUM_THREADS=1, cv2.setNumThreads(1)), the
number of points, then OpenCV's calcOpticalFlowPyrLK on the same points of the previous frame
(6 levels, 21x21 window, with and without a forward-backward check), accuracy of both against
ground truth, and the survival of tracks across frame drops.
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
from granite.optical_flow.synthetic import apply_affine, similarity, textured_image, warp  # noqa: E402

SIZE = (640, 480)


@dataclass
class Sequence:
    """Frames plus a ground-truth mapping ``gt(i, j, uv_i) -> (uv_j, valid)`` or None."""

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
    images = [warp(big, a, SIZE) for a in affines]

    def gt(i: int, j: int, uv: np.ndarray):
        back = apply_affine(cv2.invertAffineTransform(affines[i]), uv)
        return apply_affine(affines[j], back), np.ones(len(uv), bool)

    return Sequence(
        f"synthetic 640x480 texture, {n_frames} frames, 6 px + 0.3 deg + 0.2 % zoom per "
        "frame, 4-frame drops every 15 frames; ground truth: exact image motion",
        np.asarray(stamps), images, gt,
    )


def dataset_sequence(path: Path, n_frames: int, native: bool) -> Sequence:
    from granite.io import open_dataset

    ds = open_dataset(path)
    frames = [f for f in ds.frames(0, n_frames) if f.image is not None]
    if not frames:
        raise SystemExit(f"no readable frames in {path}")
    h, w = frames[0].image.shape
    notes = []
    if (w, h) != SIZE and not native:
        sx, sy = SIZE[0] / w, SIZE[1] / h
        images = [cv2.resize(f.image, SIZE, interpolation=cv2.INTER_AREA if sx < 1 else cv2.INTER_LINEAR)
                  for f in frames]
        notes.append(f"frames resized from {w}x{h} to 640x480 (x{sx:.3f}, y{sy:.3f})")
    else:
        sx = sy = 1.0
        images = [f.image for f in frames]
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
        notes.append("no ground truth (needs depth maps, poses and calibration)")
    return Sequence(f"{path} ({len(images)} frames)", np.array([f.timestamp for f in frames]),
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


def run(seq: Sequence, config: OpticalFlowConfig, compare_lk: bool) -> dict:
    flow = FrameToFrameOpticalFlow(config)
    flow.process(0.0, seq.images[0])  # numba compilation / cache load outside the timing
    flow.process(0.1, seq.images[1])
    flow = FrameToFrameOpticalFlow(config)
    lk_params = dict(winSize=(21, 21), maxLevel=config.levels - 1,
                     criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))
    stats = {k: [] for k in ("pyramid", "detection", "tracking", "points", "tracked",
                             "lk_fwd", "lk_fb", "err_ours", "err_lk", "lk_kept", "surv_drop",
                             "surv_normal", "err_drop", "err_level")}
    dt_nominal = np.median(np.diff(seq.timestamps)) if len(seq.timestamps) > 1 else 1.0
    prev = None
    prev_index = -1
    for i, img in enumerate(seq.images):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FrameRejectedWarning)
            r = flow.process(float(seq.timestamps[i]), img)
        if r.rejected:
            print(f"  frame {i} rejected: {r.rejected}")
            continue
        if prev is not None:
            for key in ("pyramid", "detection", "tracking"):
                stats[key].append(r.timing[key])
            stats["points"].append(len(r))
            _, i0, i1 = np.intersect1d(prev.ids, r.ids, return_indices=True)
            stats["tracked"].append(len(i0))
            drop = seq.timestamps[i] - seq.timestamps[prev_index] > 1.5 * dt_nominal
            stats["surv_drop" if drop else "surv_normal"].append(len(i0) / max(len(prev), 1))
            if seq.gt is not None and len(i0):
                uv_gt, ok = seq.gt(prev_index, i, prev.positions[i0])
                e = np.linalg.norm(r.positions[i1] - uv_gt, axis=1)[ok]
                stats["err_ours"].append(e)
                stats["err_level"].append(prev.levels[i0][ok])
                if drop:
                    stats["err_drop"].append(e)
            if compare_lk and len(prev):
                a, b = to_u8(seq.images[prev_index]), to_u8(img)
                p0 = prev.positions.astype(np.float32).reshape(-1, 1, 2)
                t0 = time.perf_counter()
                p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, **lk_params)
                t1 = time.perf_counter()
                pb, stb, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, **lk_params)
                t2 = time.perf_counter()
                stats["lk_fwd"].append(1e3 * (t1 - t0))
                stats["lk_fb"].append(1e3 * (t2 - t0))
                fb = np.sum((pb - p0).reshape(-1, 2) ** 2, axis=1) / 4.0 ** prev.levels
                kept = (st.ravel() == 1) & (stb.ravel() == 1) & (fb < config.fb_threshold_sq)
                stats["lk_kept"].append(kept.mean())
                if seq.gt is not None:
                    uv_gt, ok = seq.gt(prev_index, i, prev.positions)
                    both = kept & ok & np.isin(prev.ids, r.ids)
                    ours = {t: k for k, t in enumerate(r.ids)}
                    j = np.array([ours[t] for t in prev.ids[both]], dtype=np.int64)
                    stats["err_lk"].append(np.c_[
                        np.linalg.norm(p1.reshape(-1, 2)[both] - uv_gt[both], axis=1),
                        np.linalg.norm(r.positions[j] - uv_gt[both], axis=1),
                    ])
        prev, prev_index = r, i
    return stats


def describe_errors(errors: list[np.ndarray]) -> str:
    if not errors:
        return "n/a"
    e = np.concatenate(errors)
    if not len(e):
        return "n/a"
    return (f"median {np.median(e):.3f} px, 98% {np.percentile(e, 98):.3f} px, "
            f"{100 * np.mean(e > 2.0):.2f} % > 2 px (n={len(e)})")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", nargs="?", type=Path)
    parser.add_argument("--frames", type=int, default=60, help="frames to use (default 60)")
    parser.add_argument("--native", action="store_true", help="keep the dataset's image size")
    parser.add_argument("--ablation", action="store_true",
                        help="also run the ablation † (corners on the finest level only)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override an OpticalFlowConfig field (repeatable), e.g. presmooth_sigma=0.7")
    args = parser.parse_args(argv)
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key.strip()] = {"true": True, "false": False}.get(value.strip().lower(), None)
        if overrides[key.strip()] is None:
            overrides[key.strip()] = float(value) if any(c in value for c in ".eE") else int(value)
    cv2.setNumThreads(1)
    seq = (dataset_sequence(args.dataset, args.frames, args.native) if args.dataset
           else synthetic_sequence(args.frames))
    h, w = seq.images[0].shape
    print(f"input: {seq.description}; frames {w}x{h} {seq.images[0].dtype}")
    for note in seq.notes:
        print(f"  {note}")
    print("threads: one core (numba kernels single-threaded, NUMBA_NUM_THREADS=1, "
          "cv2.setNumThreads(1)); times are medians over frames")
    base = OpticalFlowConfig.from_dict(overrides)
    if overrides:
        print(f"config overrides: {overrides}")
    configs = [("ours", base)]
    if args.ablation:
        configs.append(("ours † (finest level only)",
                        OpticalFlowConfig.from_dict({**base.to_dict(), "detect_all_levels": False})))
    for name, config in configs:
        s = run(seq, config, compare_lk=name == "ours")
        med = {k: float(np.median(s[k])) for k in ("pyramid", "detection", "tracking")}
        total = sum(med.values())
        print(f"\n[{name}] ms/frame: pyramid {med['pyramid']:.2f}, detection {med['detection']:.2f}, "
              f"tracking {med['tracking']:.2f}, total {total:.2f}")
        print(f"  points per frame: {np.median(s['points']):.0f} (of which tracked from the previous "
              f"frame: {np.median(s['tracked']):.0f}); tracking {1e3 * med['tracking'] / max(np.median(s['tracked']), 1):.1f} us/point")
        print(f"  accuracy vs ground truth: {describe_errors(s['err_ours'])}")
        if s["err_level"]:
            e, lv = np.concatenate(s["err_ours"]), np.concatenate(s["err_level"])
            for c in np.unique(lv):
                print(f"    created on level {c}: {describe_errors([e[lv == c]])}")
        if s["surv_drop"]:
            print(f"  track survival: {100 * np.mean(s['surv_normal']):.1f} % per normal frame, "
                  f"{100 * np.mean(s['surv_drop']):.1f} % across frame drops ({len(s['surv_drop'])} drops); "
                  f"error across drops: {describe_errors(s['err_drop'])}")
        else:
            print(f"  track survival: {100 * np.mean(s['surv_normal']):.1f} % per frame (no frame drops)")
        if s["lk_fwd"]:
            print(f"  OpenCV calcOpticalFlowPyrLK on the same points (6 levels, 21x21): "
                  f"{np.median(s['lk_fwd']):.2f} ms forward, {np.median(s['lk_fb']):.2f} ms forward+backward; "
                  f"kept by its forward-backward check: {100 * np.mean(s['lk_kept']):.1f} %")
            if s["err_lk"]:
                e = np.concatenate(s["err_lk"])
                head = f"  on the {len(e)} tracks both kept: "
                print(f"{head}OpenCV {describe_errors([e[:, 0]])}")
                print(f"{' ' * len(head)}ours   {describe_errors([e[:, 1]])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
