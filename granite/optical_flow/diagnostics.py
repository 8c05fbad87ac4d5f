"""Measurement helpers for the frontend (benchmarks, tests): forward-backward distances
without a limit."""

from __future__ import annotations

import numpy as np

from granite.optical_flow.config import OpticalFlowConfig
from granite.optical_flow.patterns import make_pattern
from granite.optical_flow.pyramid import ImagePyramid
from granite.optical_flow.tracking import PASS_ZERO, new_template_cache, track_points


def forward_backward(
    pyr_a: ImagePyramid, pyr_b: ImagePyramid, points: np.ndarray, levels: np.ndarray,
    config: OpticalFlowConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Track ``points`` (N, 2, level-0 px, created on ``levels``) from A to B from zero motion
    and back from the result, as the reference pass does but without any forward-backward
    limit. Returns (forward positions (N, 2), forward-backward distance (N,) in pixels of
    each point's creation level; inf where either direction failed)."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    levels = np.ascontiguousarray(levels, dtype=np.int64).reshape(-1)
    n = len(points)
    pattern = make_pattern(config.pattern, config.pattern_scale)

    def one(a: ImagePyramid, b: ImagePyramid, pts: np.ndarray):
        ca = new_template_cache(n, a.num_levels, len(pattern))
        cb = new_template_cache(n, a.num_levels, len(pattern))
        return track_points(
            a.data, a.offsets, a.widths, a.heights, b.data, b.offsets, b.widths, b.heights,
            pts, levels, np.full(n, -1, np.int64), *ca, *cb,
            pattern, config.margin, config.iterations, np.inf, 0.0, order=[PASS_ZERO],
        )

    fwd, _, ok_f = one(pyr_a, pyr_b, points)
    back, _, ok_b = one(pyr_b, pyr_a, fwd)
    fb = np.linalg.norm(back - points, axis=1) / np.exp2(levels)
    fb[~(ok_f & ok_b)] = np.inf
    return fwd, fb
