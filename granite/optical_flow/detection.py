"""Grid-based FAST corner detection on several pyramid levels (paper Sec. IV-A).

On level ``l`` the image is divided into ``grid_size`` cells (level pixels), centred like the
reference: ``w // grid_size`` by ``h // grid_size`` full cells, the remainder split evenly on
both sides. A cell gets at most one new corner, and none if it already holds a point created
at level ``l - 1``, ``l`` or ``l + 1`` (points are mapped to level ``l`` by ``p / 2**l``). In a
free cell OpenCV's FAST-9 runs with the initial threshold, halved while nothing is found and
the threshold stays >= the minimum; the strongest response whose corner is at least
``border`` pixels inside the level image wins. FAST sees a 3 px ring around the cell, so
corners on cell edges are found as on the whole image.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numba import njit

from granite.optical_flow.config import OpticalFlowConfig
from granite.optical_flow.pyramid import ImagePyramid

_FAST_RING = 3


def cell_layout(width: int, height: int, grid_size: int) -> tuple[int, int, int, int]:
    """(x_start, y_start, n_cols, n_rows) of the detection grid of a width x height level."""
    return (width % grid_size) // 2, (height % grid_size) // 2, width // grid_size, height // grid_size


def occupied_cells(
    points_l: np.ndarray, width: int, height: int, grid_size: int
) -> np.ndarray:
    """Boolean (n_rows, n_cols) map of the cells holding at least one of ``points_l`` (N, 2)
    (level pixels)."""
    x0, y0, nc, nr = cell_layout(width, height, grid_size)
    occupied = np.zeros((nr, nc), dtype=bool)
    if len(points_l) == 0 or nr == 0 or nc == 0:
        return occupied
    col = np.floor((points_l[:, 0] - x0) / grid_size).astype(np.int64)
    row = np.floor((points_l[:, 1] - y0) / grid_size).astype(np.int64)
    inside = (col >= 0) & (col < nc) & (row >= 0) & (row < nr)
    occupied[row[inside], col[inside]] = True
    return occupied


def detect_in_cells(
    image_u8: np.ndarray, occupied: np.ndarray, config: OpticalFlowConfig
) -> np.ndarray:
    """At most one FAST corner per free cell of an 8-bit level image; (M, 2) float64 level
    pixels, in cell order (row-major)."""
    h, w = image_u8.shape
    g = config.grid_size
    x_start, y_start, nc, nr = cell_layout(w, h, g)
    b = config.border
    lo_x, hi_x, lo_y, hi_y = b, w - 1 - b, b, h - 1 - b
    detectors = [
        cv2.FastFeatureDetector_create(threshold=t, nonmaxSuppression=True)
        for t in config.fast_thresholds
    ]
    corners: list[tuple[float, float]] = []
    for r in range(nr):
        cy0 = y_start + r * g
        ya, yb = max(cy0, lo_y), min(cy0 + g - 1, hi_y)
        if ya > yb:
            continue
        for c in range(nc):
            if occupied[r, c]:
                continue
            cx0 = x_start + c * g
            xa, xb = max(cx0, lo_x), min(cx0 + g - 1, hi_x)
            if xa > xb:
                continue
            # Region allowed for corners is [xa, xb] x [ya, yb]; FAST needs a 3 px ring.
            rx0, ry0 = xa - _FAST_RING, ya - _FAST_RING
            roi = image_u8[ry0 : yb + _FAST_RING + 1, rx0 : xb + _FAST_RING + 1]
            best = _strongest_corner(roi, detectors)
            if best is not None:
                corners.append((best[0] + rx0, best[1] + ry0))
    return np.asarray(corners, dtype=np.float64).reshape(-1, 2)


def _strongest_corner(roi: np.ndarray, detectors) -> tuple[float, float] | None:
    h, w = roi.shape
    for detector in detectors:
        best = None
        best_key = None
        for kp in detector.detect(roi):
            x, y = kp.pt
            # Corners on the ring itself lack a full FAST circle; keep the cell interior.
            if not (_FAST_RING <= x <= w - 1 - _FAST_RING and _FAST_RING <= y <= h - 1 - _FAST_RING):
                continue
            key = (-kp.response, y, x)  # strongest first, ties broken by position
            if best_key is None or key < best_key:
                best_key = key
                best = (x, y)
        if best is not None:
            return best
    return None


@njit(cache=True, nogil=True)
def _mark_occupied(occupied, points, levels, level, x_start, y_start, grid_size) -> None:
    """``occupied[row, col] = True`` for the cells of a level's grid holding one of ``points``
    (N, 2) (level-0 pixels) created within one level of ``level``: :func:`occupied_cells` of
    ``points[near] / 2**level``, with the same floating-point operations, without the
    temporaries (the detection runs between two frames' tracking, on the critical path)."""
    nr, nc = occupied.shape
    scale = float(1 << level)
    for k in range(points.shape[0]):
        if abs(levels[k] - level) > 1:
            continue
        fx = (points[k, 0] / scale - x_start) / grid_size
        fy = (points[k, 1] / scale - y_start) / grid_size
        if not (math.isfinite(fx) and math.isfinite(fy)):
            continue
        col = math.floor(fx)
        row = math.floor(fy)
        if 0 <= col < nc and 0 <= row < nr:
            occupied[row, col] = True


def detect_new_points(
    pyramid: ImagePyramid,
    config: OpticalFlowConfig,
    points: np.ndarray,
    levels: np.ndarray,
    images_u8: dict[int, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """New corners on the configured levels given the current points.

    Args:
        points: (N, 2) level-0 positions of the tracked points; levels: (N,) creation levels.
        images_u8: the levels as 8-bit images (:meth:`ImagePyramid.level_uint8`) when made
            already (e.g. ahead of time with the pyramid); made here otherwise.
    Returns:
        (positions (M, 2) float64 level-0 pixels, levels (M,) int64). Levels are processed
        from fine to coarse; corners found on one level count as occupants for the next.
    """
    occupants = [(np.asarray(points, dtype=np.float64).reshape(-1, 2),
                  np.asarray(levels, dtype=np.int64).reshape(-1))]
    new_pts: list[np.ndarray] = []
    new_lvls: list[np.ndarray] = []
    for lvl in config.detection_levels:
        if lvl >= pyramid.num_levels:
            break
        w, h = int(pyramid.widths[lvl]), int(pyramid.heights[lvl])
        x0, y0, nc, nr = cell_layout(w, h, config.grid_size)
        occupied = np.zeros((nr, nc), dtype=bool)
        for pts, lv in occupants:
            _mark_occupied(occupied, pts, lv, lvl, x0, y0, config.grid_size)
        if occupied.size == 0 or occupied.all():
            continue
        image = images_u8[lvl] if images_u8 is not None and lvl in images_u8 else pyramid.level_uint8(lvl)
        found = detect_in_cells(image, occupied, config) * float(1 << lvl)
        if len(found):
            lv_found = np.full(len(found), lvl, dtype=np.int64)
            new_pts.append(found)
            new_lvls.append(lv_found)
            occupants.append((found, lv_found))
    if not new_pts:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    return np.concatenate(new_pts), np.concatenate(new_lvls)
