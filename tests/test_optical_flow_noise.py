"""Image-noise estimate, pyramid noise gains, the expected tracking precision of a patch
(sigma² (J^T J)^-1) and the noise-scaled forward-backward limit, each against an independent
computation."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from granite.optical_flow import OpticalFlowConfig
from granite.optical_flow.diagnostics import forward_backward
from granite.optical_flow.noise import estimate_noise, level_noise_gains, unit_noise_std
from granite.optical_flow.patch import make_template
from granite.optical_flow.patterns import pattern52
from granite.optical_flow.pyramid import build_pyramid
from granite.optical_flow.synthetic import add_noise, similarity, textured_image, warp
from granite.optical_flow.tracking import PASS_ZERO, new_template_cache, track_points

H, W = 240, 320


def smooth_texture(seed: int = 0) -> np.ndarray:
    """A float image without fine structure (the noise estimator should not see it)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.standard_normal((H, W)), (0, 0), 6.0)
    return 128.0 + 40.0 * img / img.std()


@pytest.mark.parametrize("sigma", [1.0, 3.0])
def test_noise_estimate_recovers_white_noise_on_a_smooth_image(sigma):
    rng = np.random.default_rng(3)
    img = np.clip(np.rint(smooth_texture() + sigma * rng.standard_normal((H, W))), 0, 255).astype(np.uint8)
    est = estimate_noise(img, stride=1)
    # rounding to integers adds 1/12 DN² of variance
    assert est == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.08)
    assert estimate_noise(img, stride=4) == pytest.approx(est, rel=0.1)
    assert estimate_noise(np.full((H, W), 77, np.uint8)) == 0.0


def _gaussian_taps(sigma: float) -> np.ndarray:
    """The 1-D kernel OpenCV's GaussianBlur uses for float images (size round(8 sigma + 1) | 1)."""
    size = int(round(sigma * 8 + 1)) | 1
    return cv2.getGaussianKernel(size, sigma, cv2.CV_64F).ravel()


@pytest.mark.parametrize("presmooth", [0.0, 0.7])
def test_level_noise_gains_match_the_filter_cascade(presmooth):
    """Independent computation: the 1-D impulse response g_l of pre-smoothing and l times
    pyrDown (kernel [1 4 6 4 1]/16, taps 2^k apart at step k); white noise of unit variance
    gives level l a standard deviation sum(g_l²) (the 2-D response is g_l x g_l)."""
    k = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    g = _gaussian_taps(presmooth) if presmooth > 0 else np.array([1.0])
    gains = level_noise_gains(6, presmooth)
    for lvl in range(6):
        if lvl:
            up = np.zeros(4 * 2 ** (lvl - 1) + 1)
            up[:: 2 ** (lvl - 1)] = k
            g = np.convolve(g, up)
        assert gains[lvl] == pytest.approx(np.sum(g**2), rel=0.04), lvl


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    ix, iy = np.floor(x).astype(int), np.floor(y).astype(int)
    dx, dy = x - ix, y - iy
    i = img.astype(np.float64)
    return ((1 - dx) * (1 - dy) * i[iy, ix] + dx * (1 - dy) * i[iy, ix + 1]
            + (1 - dx) * dy * i[iy + 1, ix] + dx * dy * i[iy + 1, ix + 1])


def _patch_jacobian_fd(img: np.ndarray, cx: float, cy: float, pattern: np.ndarray, eps: float = 0.25):
    """J of the mean-normalised pattern intensities w.r.t. (tx, ty, theta) (pattern-side
    increment) by central finite differences of float64 bilinear samples, and the mean."""
    def samples(tx, ty, th):
        c, s = np.cos(th), np.sin(th)
        qx = c * pattern[:, 0] - s * pattern[:, 1] + tx
        qy = s * pattern[:, 0] + c * pattern[:, 1] + ty
        v = _bilinear(img, cx + qx, cy + qy)
        return v / v.mean(), v.mean()
    steps = np.diag([eps, eps, eps / 5.0])
    cols = [(samples(*d)[0] - samples(*(-d))[0]) / (2 * d.max()) for d in steps]
    return np.stack(cols, axis=1), samples(0, 0, 0)[1]


def test_expected_tracking_std_matches_an_independent_jacobian():
    # smooth at the pixel scale, so that finite differences and make_template's central
    # differences of bilinear samples measure the same gradient
    img = cv2.GaussianBlur(textured_image(H, W, seed=4).astype(np.float32), (0, 0), 1.5)
    pattern = pattern52(0.75)
    pts = np.array([[100.3, 80.6], [200.0, 150.0], [60.5, 170.25]])
    got = unit_noise_std(img.ravel(), 0, W, H, pts, pattern, 2.0)
    for (cx, cy), value in zip(pts, got):
        J, mean = _patch_jacobian_fd(img, cx, cy, pattern)
        C = np.linalg.inv(J.T @ J)[:2, :2]
        assert value == pytest.approx(np.sqrt(np.linalg.eigvalsh(C).max()) / mean, rel=0.05)


def test_expected_tracking_std_predicts_the_scatter_of_tracks_under_noise():
    """Monte Carlo: a clean template tracked into the same image plus white noise of sigma
    DN scatters with covariance f sigma² C / mean² (C from the template), where f = 0.625² is
    the variance of bilinearly interpolated noise at the pattern's sample positions (fractions
    0.25 / 0.75 on both axes for integer centres); the largest eigenvalue of the empirical
    covariance agrees with 0.625 sigma unit_noise_std within 20 %."""
    base = cv2.GaussianBlur(textured_image(H, W, seed=8).astype(np.float32), (0, 0), 1.0)
    clean = np.clip(np.rint(base), 0, 255).astype(np.uint8)
    pattern = pattern52(0.75)
    cfg = OpticalFlowConfig(levels=1, presmooth_sigma=0.0)
    pts = np.array([[x, y] for x in (70.0, 130.0, 190.0, 250.0) for y in (60.0, 120.0, 180.0)])
    levels = np.zeros(len(pts), np.int64)
    pyr_a = build_pyramid(clean, 1)
    predicted = unit_noise_std(pyr_a.data, 0, W, H, pts, pattern, 2.0)
    sigma = 4.0
    rng = np.random.default_rng(11)
    estimates = []
    for _ in range(150):
        noisy = np.clip(base + sigma * rng.standard_normal(base.shape), 0, 255).astype(np.float32)
        # float image: no rounding noise; build the level by hand (build_pyramid wants ints)
        buf = np.ascontiguousarray(noisy).ravel()
        offs, ws, hs = np.zeros(1, np.int64), np.array([W]), np.array([H])
        ca = new_template_cache(len(pts), 1, len(pattern))
        cb = new_template_cache(len(pts), 1, len(pattern))
        out, _, ok = track_points(
            pyr_a.data, pyr_a.offsets, pyr_a.widths, pyr_a.heights, buf, offs, ws, hs,
            pts, levels, np.full(len(pts), -1), *ca, *cb, pattern, cfg.margin, 20, np.inf, 0.0,
            order=[PASS_ZERO],
        )
        assert ok.all()
        estimates.append(out - pts)
    e = np.stack(estimates)  # (runs, points, 2)
    for k in range(len(pts)):
        lam = np.linalg.eigvalsh(np.cov(e[:, k].T)).max()
        assert np.sqrt(lam) == pytest.approx(0.625 * sigma * predicted[k], rel=0.2), k


def test_noise_scaled_limit_is_the_clipped_patch_variance():
    """Status of every track = its forward-backward distance below
    clip(fb_var * lambda_max(C) / mean², fb_threshold_sq, fb_max_sq), with C and the mean
    computed here independently of the kernel."""
    img0 = add_noise(textured_image(H, W, seed=2, contrast=0.3), 3.0, 0.0, 1)
    img1 = add_noise(warp(textured_image(H, W, seed=2, contrast=0.3), similarity(2.3, -1.4, 0.01, 1.0, (W / 2, H / 2))), 3.0, 0.0, 2)
    cfg = OpticalFlowConfig(presmooth_sigma=0.0, pattern="pattern52")
    pa, pb = build_pyramid(img0, cfg.levels), build_pyramid(img1, cfg.levels)
    xs, ys = np.meshgrid(np.arange(30.0, W - 30, 23.0), np.arange(30.0, H - 30, 21.0))
    pts = np.c_[xs.ravel(), ys.ravel()]
    levels = np.zeros(len(pts), np.int64)
    _, fb = forward_backward(pa, pb, pts, levels, cfg)
    pattern = pattern52(cfg.pattern_scale)
    lam_over_mean_sq = np.empty(len(pts))
    level0 = pa.level(0)
    for k, (cx, cy) in enumerate(pts):
        data = np.empty(52, np.float32)
        valid = np.empty(52, np.bool_)
        jac = np.empty((52, 3), np.float32)
        aux = np.empty((5, 3), np.float32)
        assert make_template(pa.data, 0, W, H, cx, cy, pattern, 2.0, data, valid, jac, aux) == 2
        mean = cv2.remap(level0, (pattern[:, 0] + cx).astype(np.float32)[None],
                         (pattern[:, 1] + cy).astype(np.float32)[None], cv2.INTER_LINEAR).mean()
        lam_over_mean_sq[k] = np.linalg.eigvalsh(aux[:2, :2].astype(np.float64)).max() / mean**2
    fb_var = np.zeros(cfg.levels)
    fb_var[0] = np.median(fb[np.isfinite(fb)] ** 2 / lam_over_mean_sq[np.isfinite(fb)])  # about half pass
    lo, hi = 1e-4, 0.05
    n = len(pts)
    ca, cb = new_template_cache(n, cfg.levels, 52), new_template_cache(n, cfg.levels, 52)
    _, _, status = track_points(
        pa.data, pa.offsets, pa.widths, pa.heights, pb.data, pb.offsets, pb.widths, pb.heights,
        pts, levels, np.full(n, -1), *ca, *cb, pattern, cfg.margin, cfg.iterations, lo, 0.0,
        order=[PASS_ZERO], fb_var=fb_var, fb_max_sq=hi,
    )
    limit = np.clip(fb_var[0] * lam_over_mean_sq, lo, hi)
    expected = fb**2 < limit
    # compare where both directions converged, away from float rounding at the boundary
    use = np.isfinite(fb) & (np.abs(fb**2 / limit - 1.0) > 1e-3)
    assert use.sum() > 0.9 * n and 0.2 < expected[use].mean() < 0.8
    assert np.array_equal(status[use], expected[use])
    # without the scaled limit the fixed one applies
    ca, cb = new_template_cache(n, cfg.levels, 52), new_template_cache(n, cfg.levels, 52)
    _, _, fixed = track_points(
        pa.data, pa.offsets, pa.widths, pa.heights, pb.data, pb.offsets, pb.widths, pb.heights,
        pts, levels, np.full(n, -1), *ca, *cb, pattern, cfg.margin, cfg.iterations, 0.03, 0.0,
        order=[PASS_ZERO],
    )
    use = np.isfinite(fb) & (np.abs(fb**2 / 0.03 - 1.0) > 1e-3)
    assert np.array_equal(fixed[use], (fb**2 < 0.03)[use])


def test_noise_scaled_limit_keeps_more_weak_patches_under_noise():
    """End to end: on a low-contrast noisy pair, fb_noise_factor = 3 keeps more tracks than
    the fixed limit, and the kept ones stay accurate."""
    tex = textured_image(H, W, seed=6, contrast=0.25)
    affine = similarity(3.1, 1.7, 0.0, 1.0, (W / 2, H / 2))
    frames = [add_noise(tex, 4.0, 0.0, 1), add_noise(warp(tex, affine), 4.0, 0.0, 2)]
    kept = {}
    for factor in (0.0, 3.0):
        from granite.optical_flow import FrameToFrameOpticalFlow

        flow = FrameToFrameOpticalFlow(OpticalFlowConfig(presmooth_sigma=0.0, pattern="pattern52",
                                                      fb_noise_factor=factor))
        r0 = flow.process(0.0, frames[0])
        r1 = flow.process(0.1, frames[1])
        _, i0, i1 = np.intersect1d(r0.ids, r1.ids, return_indices=True)
        truth = r0.positions[i0] @ affine[:, :2].T + affine[:, 2]
        err = np.linalg.norm(r1.positions[i1] - truth, axis=1)
        kept[factor] = len(i0) / len(r0)
        assert np.median(err) < 0.3 and np.mean(err > 1.0) < 0.02
    assert kept[3.0] > kept[0.0] + 0.03
