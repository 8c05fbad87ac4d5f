"""Re-finding lost points from their predicted positions (recovery across frame drops).

After a gap (dropped frames, fast motion) frame-to-frame tracks are torn apart, but the
estimator still knows where the window's landmarks should appear. :func:`refind_points` tracks
each point's patch from the image it was created in (its host keyframe) into the current image,
starting at the predicted position, with the frontend's own kernels (coarse-to-fine SE(2)
inverse-compositional KLT, :func:`granite.optical_flow.tracking.track_point`). A re-found point
is kept only if

* tracking it back from the found position into the host image returns within
  ``fb_threshold_sq`` (squared pixels of its creation level) of where it was created, and
* the zero-mean normalised cross-correlation of the patch at the found position with the host
  template (creation level, :func:`granite.optical_flow.patch.patch_zncc`) is at least
  ``min_zncc`` (the backward pass starts near the host position, so without it a wrong match
  reached from a wrong prediction could still pass the first check).

Not in the reference (which has no re-finding). The settings are ``[estimator]`` keys.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from granite.optical_flow.patch import FASTMATH, patch_zncc, pattern_radius, template_workspace
from granite.optical_flow.pyramid import ImagePyramid
from granite.optical_flow.tracking import track_point


@njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def _refind(buf_h, offs_h, ws_h, hs_h, buf_c, offs_c, ws_c, hs_c, host_uv, levels, guess_uv,
            pattern, margin, iterations, fb_threshold_sq, min_zncc):
    n = host_uv.shape[0]
    n_levels = offs_h.shape[0]
    p = pattern.shape[0]
    out = np.full((n, 2), np.nan)
    ok_all = np.zeros(n, dtype=np.bool_)
    zncc = np.full(n, -2.0)
    st, data, valid, jac, aux = template_workspace(n_levels, p)
    st_b, data_b, valid_b, jac_b, aux_b = template_workspace(n_levels, p)
    radius = pattern_radius(pattern)
    for k in range(n):
        x0 = host_uv[k, 0]
        y0 = host_uv[k, 1]
        gx = guess_uv[k, 0]
        gy = guess_uv[k, 1]
        lvl = levels[k]
        if not (math.isfinite(gx) and math.isfinite(gy)) or lvl >= n_levels:
            continue
        st[:] = -1
        ok, x1, y1, t1 = track_point(
            buf_h, offs_h, ws_h, hs_h, buf_c, offs_c, ws_c, hs_c,
            x0, y0, gx, gy, lvl, pattern, radius, margin, iterations, st, data, valid, jac, aux,
        )
        if not ok:
            continue
        st_b[:] = -1
        ok, xb, yb, _ = track_point(
            buf_c, offs_c, ws_c, hs_c, buf_h, offs_h, ws_h, hs_h,
            x1, y1, x0, y0, lvl, pattern, radius, margin, iterations,
            st_b, data_b, valid_b, jac_b, aux_b,
        )
        if not ok:
            continue
        scale = float(1 << lvl)
        dx = (xb - x0) / scale
        dy = (yb - y0) / scale
        if dx * dx + dy * dy >= fb_threshold_sq:
            continue
        if st[lvl] <= 0:
            continue
        zn = patch_zncc(buf_c, offs_c[lvl], ws_c[lvl], hs_c[lvl], x1 / scale, y1 / scale, t1,
                        pattern, margin, data[lvl], valid[lvl])
        zncc[k] = zn
        if zn < min_zncc:
            continue
        out[k, 0] = x1
        out[k, 1] = y1
        ok_all[k] = True
    return out, ok_all, zncc


def refind_points(host: ImagePyramid, current: ImagePyramid, host_uv: np.ndarray,
                  levels: np.ndarray, predicted_uv: np.ndarray, pattern: np.ndarray,
                  margin: float, iterations: int, fb_threshold_sq: float,
                  min_zncc: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track points created at ``host_uv`` (level-0 pixels, (n, 2)) on pyramid level
    ``levels`` (n,) of ``host`` into ``current``, starting at ``predicted_uv`` (n, 2; NaN rows
    are skipped). Returns the found positions (n, 2; NaN where rejected), the acceptance mask
    (n,) and the ZNCC of each match (n,; -2 where it was not computed)."""
    host_uv = np.ascontiguousarray(host_uv, dtype=np.float64).reshape(-1, 2)
    predicted_uv = np.ascontiguousarray(predicted_uv, dtype=np.float64).reshape(-1, 2)
    levels = np.ascontiguousarray(levels, dtype=np.int64).reshape(-1)
    if not (len(host_uv) == len(predicted_uv) == len(levels)):
        raise ValueError("host_uv, levels and predicted_uv must have the same length")
    if current.num_levels != host.num_levels:
        raise ValueError("host and current pyramids must have the same number of levels")
    return _refind(host.data, host.offsets, host.widths, host.heights,
                   current.data, current.offsets, current.widths, current.heights,
                   host_uv, levels, predicted_uv, np.ascontiguousarray(pattern, dtype=np.float64),
                   float(margin), int(iterations), float(fb_threshold_sq), float(min_zncc))
