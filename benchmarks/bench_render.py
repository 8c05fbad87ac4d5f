"""Seconds per 640x480 frame of the spiral scenario (Cycles CPU, the scenario's clean-quality
settings: 4 samples, no denoiser, direct sun + analytic sky light).

    python benchmarks/bench_render.py [--frames 8] [--samples N] [--corners] [--save DIR]
                                      [--plain-terrain] [--reference-samples 64]
                                      [--denoise] [--adaptive-threshold T
                                      [--adaptive-min-samples N]]

Prints the wall time per frame (after one warm-up frame that builds the BVH), the process CPU
time per frame divided by the render threads (what the time would be on an idle machine),
the time of the sensor model per frame, and the load average (the machine may be shared).
``--plain-terrain`` renders the terrain of before the realism work (no ripples, power-law
rocks from 0.1 m) for an A/B comparison of the appearance cost in the same conditions. ``--corners`` also prints the number of
FAST corners (OpenCV, threshold 20) per frame and its altitude; ``--save`` writes the frames
(with ``--reference-samples`` also the reference's and both raw float renders as .npy).

``--reference-samples N`` measures the image quality: every timed frame i comes with its
successor i + 1 (also timed), and after the timed renders all of them are rendered again with
N samples, no adaptive sampling and no denoiser (not timed; :meth:`Renderer.reconfigure`,
without which the persistent Cycles session would keep the first render's sample count).
Printed per frame and as mean / min:

- PSNR of the clean render (Cycles' linear radiance, before the sensor model): on the Rec. 709
  luminance, render and reference both divided by the reference's 99.5th percentile and clipped
  to [0, 1]; and the largest raw float difference (0 = the image does not depend on the
  sample count);
- PSNR after the sensor model (the 8-bit grayscale images the VO reads; the sensor's noise is
  seeded by the frame index, so both carry the same noise and the difference is the render's);
- level-0 tracks of our frontend (``granite.optical_flow`` defaults, as ``granite track``) from
  frame i to i + 1 on the sensor images, render and reference: the share of the level-0 tracks
  detected in frame i still tracked in frame i + 1 (survival) and the median error of the
  surviving ones against the ground-truth flow (depth of frame i and the poses), medians over
  the pairs.

About 15x the render time per reference frame at 64 samples: ``--frames 4`` keeps it to 8
reference frames.
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
    ap.add_argument("--denoise", action="store_true",
                    help="OpenImageDenoise on the render (CPU, albedo and normal passes)")
    ap.add_argument("--adaptive-threshold", type=float, default=None, metavar="T",
                    help="Cycles adaptive sampling with noise threshold T (0 = off)")
    ap.add_argument("--adaptive-min-samples", type=int, default=None, metavar="N",
                    help="with --adaptive-threshold: samples every pixel gets (default: "
                         "min(samples, 4))")
    ap.add_argument("--corners", action="store_true", help="FAST corners per altitude")
    ap.add_argument("--save", type=Path, default=None, help="write the frames as PNG here")
    ap.add_argument("--plain-terrain", action="store_true",
                    help="no ripples, power-law rocks (the terrain before the realism work)")
    ap.add_argument("--reference-samples", type=int, default=None, metavar="N",
                    help="PSNR and track survival against renders with N samples (e.g. 64)")
    ap.add_argument("--reference-cache", type=Path, default=None, metavar="DIR",
                    help="keep the reference renders here and reuse them in later runs")
    args = ap.parse_args()
    if args.frames < 1:
        print("error: --frames must be at least 1", file=sys.stderr)
        return 2
    if args.reference_samples is not None and not 1 <= args.reference_samples <= 4096:
        print("error: --reference-samples must be in 1..4096", file=sys.stderr)
        return 2

    import dataclasses

    from simulation.plan import make_plan
    from simulation.render import Renderer, software_versions
    from simulation.scenario import load_scenario, with_overrides
    from simulation.terrain.scene import build_world

    from simulation.sensor import Sensor, blur_taps

    from granite.errors import ConfigError

    try:
        s = with_overrides(load_scenario("spiral"), width=640, height=480, samples=args.samples)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    render_changes = {}
    if args.denoise:
        render_changes["denoise"] = True
    if args.adaptive_threshold is not None:
        if not 0.0 <= args.adaptive_threshold <= 1.0:
            print("error: --adaptive-threshold must be in [0, 1]", file=sys.stderr)
            return 2
        render_changes["adaptive_threshold"] = args.adaptive_threshold
    if args.adaptive_min_samples is not None:
        if not 1 <= args.adaptive_min_samples <= s.render.samples:
            print("error: --adaptive-min-samples must be in 1..samples", file=sys.stderr)
            return 2
        render_changes["adaptive_min_samples"] = args.adaptive_min_samples
    s = dataclasses.replace(s, render=dataclasses.replace(s.render, **render_changes))
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
    frames = [int(i) for i in idx[1:]]
    if args.reference_samples:  # successors for the track survival
        frames = [j for i in frames for j in (i, i + 1)]
    walls, cpus, sensor_ms = [], [], []
    renders: dict[int, tuple] = {}  # frame -> (linear RGB, sensor image), for the reference
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)

    def capture(i, rgb, depth):
        e = s.sensor.exposure_time
        taps = blur_taps(depth, s.camera, plan.poses[i], plan.exposure_poses(i, e, 2))
        img, _ = sensor.capture(rgb, int(i), depth, plan.poses[i],
                                plan.exposure_poses(i, e, taps) if sensor.blurs else None)
        return img

    with Renderer(s) as renderer:
        renderer.render(plan.poses[idx[0]])  # warm-up: BVH, shaders, images
        for i in frames:
            w0, c0 = time.perf_counter(), _cpu()
            rgb, depth = renderer.render(plan.poses[i])
            walls.append(time.perf_counter() - w0)
            cpus.append((_cpu() - c0) / s.render.threads)
            w0 = time.perf_counter()
            img = capture(i, rgb, depth)
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
            if args.reference_samples:
                renders[i] = (rgb, img)
        load = os.getloadavg()[0]  # of the timed renders (the reference renders come next)
        quality = None
        if args.reference_samples:
            quality = _reference(renderer, s, plan, renders, args.reference_samples, capture,
                                 args.save, args.reference_cache)
    import _host  # benchmarks/_host.py

    v = software_versions()
    print(f"Blender {v['blender']}, {s.render.threads} threads, {s.render.samples} samples"
          f" (adaptive threshold {s.render.adaptive_threshold:g}, denoiser "
          f"{'on' if s.render.denoise else 'off'}), 640x480; plan {t_plan:.1f} s, scene build "
          f"{t_build:.1f} s; load average {load:.2f}")
    print(f"seconds per 640x480 frame: mean {np.mean(walls):.2f}, median {np.median(walls):.2f}"
          f" (wall); CPU / threads: mean {np.mean(cpus):.2f}; sensor model "
          f"{np.mean(sensor_ms):.0f} ms (grayscale); {_host.probe_text(_host.speed_probe())}")
    if quality:
        for line in quality:
            print(line)
    return 0


def _psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def clean_psnr(rgb: np.ndarray, ref: np.ndarray) -> float:
    """PSNR (dB) of the linear render ``rgb`` against ``ref`` on the Rec. 709 luminance, both
    divided by the reference's 99.5th percentile and clipped to [0, 1]."""
    from simulation.sensor import LUMA_709

    lum, ref_lum = rgb @ LUMA_709, ref @ LUMA_709
    scale = max(float(np.percentile(ref_lum, 99.5)), 1e-12)
    return _psnr(np.clip(lum / scale, 0, 1), np.clip(ref_lum / scale, 0, 1), 1.0)


def level0_tracks(img_a: np.ndarray, img_b: np.ndarray, dt: float, gt) -> tuple[float, int, float]:
    """Our frontend (a fresh one, default configuration) on ``img_a`` then ``img_b``: (share
    of its level-0 tracks of ``img_a`` still tracked in ``img_b``, their number, median error
    in px of the surviving ones against the ground-truth flow ``gt(uv_a) -> (uv_b, valid)``)."""
    from granite.optical_flow import FrameToFrameOpticalFlow

    flow = FrameToFrameOpticalFlow()
    a = flow.process(0.0, img_a)
    b = flow.process(dt, img_b)
    level0 = a.levels == 0
    if not level0.any():
        return float("nan"), 0, float("nan")
    _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    keep = level0[ia]
    uv_gt, ok = gt(a.positions[ia[keep]])
    err = np.linalg.norm(b.positions[ib[keep]] - uv_gt, axis=1)[ok]
    return (float(keep.sum() / level0.sum()), int(level0.sum()),
            float(np.median(err)) if len(err) else float("nan"))


def _reference(renderer, s, plan, renders: dict, samples: int, capture, save,
               cache: Path | None) -> list[str]:
    """Render the frames of ``renders`` again with ``samples`` samples (no adaptive sampling,
    no denoiser) and compare (module docstring); the summary lines. With ``cache``, reference
    renders are read from / written to it, named by frame and a hash of the reference's
    scenario (every setting but the render's own sample count, adaptive threshold and
    denoiser, which the reference replaces)."""
    import dataclasses
    import hashlib

    from simulation.sensor import LUMA_709

    ref_cfg = dataclasses.replace(s.render, samples=samples, adaptive_threshold=0.0,
                                  adaptive_min_samples=0, denoise=False)
    key = hashlib.sha1(repr(dataclasses.replace(s, render=ref_cfg)).encode()).hexdigest()[:12]
    if cache:
        cache.mkdir(parents=True, exist_ok=True)
    configured = False
    rows, walls = {}, []
    for i, (rgb, img) in renders.items():
        path = cache / f"spiral_{i:05d}_{samples}spp_{key}.npz" if cache else None
        if path is not None and path.exists():
            with np.load(path) as z:
                ref, depth = z["rgb"], z["depth"]
        else:
            if not configured:
                renderer.reconfigure(ref_cfg)
                configured = True
            w0 = time.perf_counter()
            ref, depth = renderer.render(plan.poses[i])
            walls.append(time.perf_counter() - w0)
            if path is not None:
                np.savez(path, rgb=ref, depth=depth)
        ref_img = capture(i, ref, depth)
        diff = float(np.max(np.abs(rgb.astype(np.float64) - ref)))
        rows[i] = (clean_psnr(rgb, ref), _psnr(img, ref_img, float(np.iinfo(img.dtype).max)),
                   diff, ref_img, float(np.percentile(ref @ LUMA_709, 99.5)), depth)
        print(f"frame {i:5d}  against {samples} samples: PSNR {rows[i][0]:.1f} dB clean, "
              f"{rows[i][1]:.1f} dB after the sensor; max |raw difference| {diff:.3g}",
              flush=True)
        if save:  # the sensor images and the raw float renders
            cv2.imwrite(str(save / f"spiral_{i:05d}_ref{samples}.png"), ref_img)
            np.save(save / f"spiral_{i:05d}_rgb.npy", rgb)
            np.save(save / f"spiral_{i:05d}_ref{samples}_rgb.npy", ref)
    from granite.optical_flow.gt_flow import ground_truth_flow
    from simulation.writer import calibration_of

    camera = calibration_of(s.camera).camera()
    dt = float(plan.times[1] - plan.times[0])
    surv, surv_ref, tracks, err, err_ref = [], [], [], [], []
    for i in renders:
        if i + 1 in renders and i - 1 not in renders:
            def gt(uv, i=i):
                return ground_truth_flow(uv, rows[i][5], plan.poses[i], plan.poses[i + 1], camera)

            x, m, e = level0_tracks(renders[i][1], renders[i + 1][1], dt, gt)
            y, _, e_ref = level0_tracks(rows[i][3], rows[i + 1][3], dt, gt)
            surv.append(x)
            surv_ref.append(y)
            tracks.append(m)
            err.append(e)
            err_ref.append(e_ref)
    peaks = [r[4] for r in rows.values()]
    clean = [r[0] for r in rows.values()]
    after = [r[1] for r in rows.values()]
    diff = max(r[2] for r in rows.values())
    rendered = f"{np.mean(walls):.1f} s per frame (wall)" if walls else f"read from {cache}"
    out = [f"reference: {samples} samples, no adaptive sampling, no denoiser; {rendered}",
           f"PSNR against {samples} samples, clean (linear luminance before the sensor model): "
           f"mean {np.mean(clean):.1f} dB, min {np.min(clean):.1f} dB; max |raw difference| "
           f"{diff:.3g} (luminance 99.5th percentiles {min(peaks):.2f}-{max(peaks):.2f})",
           f"PSNR against {samples} samples after the sensor model (8-bit, same noise): "
           f"mean {np.mean(after):.1f} dB, min {np.min(after):.1f} dB"]
    if surv:
        out.append(f"level-0 tracks, frame i -> i+1 ({len(surv)} pairs, {np.mean(tracks):.0f} "
                   f"level-0 tracks each), survival median (min) / median error against the "
                   f"ground-truth flow: {s.render.samples} samples {np.median(surv):.3f} "
                   f"({np.min(surv):.3f}) / {np.median(err):.3f} px, {samples} samples "
                   f"{np.median(surv_ref):.3f} ({np.min(surv_ref):.3f}) / "
                   f"{np.median(err_ref):.3f} px")
    if diff == 0 and samples != s.render.samples:
        out.append(f"the renders at {s.render.samples} and {samples} samples are bit-identical: "
                   "the image does not depend on the sample count")
    return out


if __name__ == "__main__":
    sys.exit(main())
