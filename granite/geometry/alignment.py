"""Least-squares similarity / rigid alignment of point sets (Umeyama 1991)."""

from __future__ import annotations

import numpy as np


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool
) -> tuple[float, np.ndarray, np.ndarray]:
    """Find ``(s, R, t)`` minimising ``sum |dst_i - (s R src_i + t)|^2``.

    ``src``, ``dst``: (N, 3) corresponding points (e.g. estimated and ground-truth positions);
    the result maps ``src`` into ``dst``'s frame. ``R`` is a proper rotation (reflections are
    excluded as in Umeyama's paper); ``s = 1`` when ``with_scale`` is False. Raises
    ``ValueError`` for N < 3, mismatched shapes, non-finite values or degenerate
    configurations (coincident or collinear points).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(
            f"src and dst must both have shape (N, 3), got {src.shape} and {dst.shape}"
        )
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"umeyama alignment needs at least 3 point pairs, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise ValueError("umeyama alignment: non-finite point coordinates")
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    var_s = float(np.mean(np.sum(xs * xs, axis=1)))
    var_d = float(np.mean(np.sum(xd * xd, axis=1)))
    scale_ref = max(var_s, var_d, float(np.max(np.abs(src))) ** 2, float(np.max(np.abs(dst))) ** 2)
    if var_s <= 1e-24 * max(scale_ref, 1e-300) or var_d <= 1e-24 * max(scale_ref, 1e-300):
        raise ValueError("umeyama alignment is degenerate: all points coincide")
    cov = xd.T @ xs / n
    U, d, Vt = np.linalg.svd(cov)
    if d[1] <= 1e-10 * d[0]:
        raise ValueError("umeyama alignment is degenerate: points are collinear")
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float(np.sum(d * S) / var_s) if with_scale else 1.0
    t = mu_d - s * (R @ mu_s)
    return s, R, t
