"""Synthetic textured images and known image warps, for tests and benchmarks.

Warps use OpenCV's affine convention: a point ``p`` of the source image appears at
``A[:, :2] @ p + A[:, 2]`` in the warped image (pixel centres at integer coordinates, the
top-left one at (0, 0)), so tracked positions can be compared with the analytic mapping.
"""

from __future__ import annotations

import cv2
import numpy as np


def textured_image(height: int, width: int, seed: int = 0, contrast: float = 1.0) -> np.ndarray:
    """Deterministic uint8 texture: band-passed noise at three scales plus random blobs.

    ``contrast`` scales the deviations from mid-grey (1.0 spans most of 0..255).
    """
    rng = np.random.default_rng(seed)
    img = np.zeros((height, width), np.float32)
    for sigma, amplitude in ((1.2, 25.0), (3.0, 30.0), (8.0, 25.0)):
        noise = cv2.GaussianBlur(rng.standard_normal((height, width)).astype(np.float32), (0, 0), sigma)
        img += amplitude * noise / max(float(noise.std()), 1e-6)
    n_blobs = max(1, height * width // 4000)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    blobs = np.zeros_like(img)
    for cx, cy, r, a in zip(
        rng.uniform(0, width, n_blobs), rng.uniform(0, height, n_blobs),
        rng.uniform(2.0, 9.0, n_blobs), rng.uniform(-60.0, 60.0, n_blobs),
    ):
        x0, x1 = int(max(cx - 3 * r, 0)), int(min(cx + 3 * r + 1, width))
        y0, y1 = int(max(cy - 3 * r, 0)), int(min(cy + 3 * r + 1, height))
        d2 = (xx[y0:y1, x0:x1] - cx) ** 2 + (yy[y0:y1, x0:x1] - cy) ** 2
        blobs[y0:y1, x0:x1] += a * np.exp(-0.5 * d2 / r**2)
    img = 128.0 + contrast * (img + blobs)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def similarity(tx: float, ty: float, angle: float, scale: float, centre: tuple[float, float]) -> np.ndarray:
    """2x3 affine: rotate by ``angle`` (rad; OpenCV's sign: positive is counter-clockwise as
    displayed) and scale about ``centre``, then translate by (tx, ty)."""
    a = cv2.getRotationMatrix2D((float(centre[0]), float(centre[1])), float(np.degrees(angle)), float(scale))
    a[:, 2] += (tx, ty)
    return a


def warp(image: np.ndarray, affine: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """Warp ``image`` by ``affine`` (bilinear, reflected border) to ``size`` = (w, h)."""
    h, w = image.shape[:2]
    return cv2.warpAffine(
        image, affine, size or (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )


def apply_affine(affine: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 2) points with a 2x3 affine."""
    return points @ affine[:, :2].T + affine[:, 2]


def add_noise(image: np.ndarray, read_sigma: float, gain: float = 0.0, seed=0) -> np.ndarray:
    """Seeded sensor-like noise on an 8- or 16-bit image: Gaussian with variance
    ``read_sigma**2 + gain * I`` (intensity units: read noise plus a Poisson-like,
    signal-dependent shot-noise term), rounded and saturated to the input dtype. ``seed`` is
    anything :func:`numpy.random.default_rng` accepts (e.g. ``(seed, frame_index)``)."""
    rng = np.random.default_rng(seed)
    img = image.astype(np.float64)
    sd = np.sqrt(read_sigma**2 + gain * np.maximum(img, 0.0))
    top = float(np.iinfo(image.dtype).max)
    return np.clip(np.rint(img + sd * rng.standard_normal(img.shape)), 0.0, top).astype(image.dtype)
