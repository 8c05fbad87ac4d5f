"""Initial guesses for a new frame: the constant-velocity pose and where tracks should appear.

Not in the reference, which starts every frame from the last pose and tracks from the last
positions (``constant_velocity = false``, ``motion_guided_tracking = false``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from granite.backend import SlidingWindow
from granite.geometry import kabsch_rotation, se3_exp, se3_inverse, se3_log
from granite.optical_flow.prediction import predict_positions


class ConstantVelocityModel:
    """The last pose ``T_w_c`` and time, and the last relative motion ``T_prev_last`` with its
    time step, of the current sub-map."""

    def __init__(self, constant_velocity: bool, max_extrapolation: float):
        self.constant_velocity = constant_velocity
        self.max_extrapolation = max_extrapolation
        self.last_pose = np.eye(4)
        self.last_time = 0.0
        self._motion: tuple[np.ndarray, float] | None = None

    @property
    def has_motion(self) -> bool:
        return self._motion is not None

    def reset(self) -> None:
        """A new sub-map starts at the identity, without motion (the time is kept)."""
        self.last_pose = np.eye(4)
        self._motion = None

    def update(self, T_w_c: np.ndarray, timestamp: float, measure_motion: bool) -> None:
        """The estimate of a processed frame; with ``measure_motion`` the step from the last
        one becomes the motion (only within a map: before it, translation is not estimated)."""
        if measure_motion:
            self._motion = (se3_inverse(self.last_pose) @ T_w_c, timestamp - self.last_time)
        self.last_pose, self.last_time = T_w_c, timestamp

    def copy(self) -> ConstantVelocityModel:
        """An independent copy (the state at this moment)."""
        other = ConstantVelocityModel(self.constant_velocity, self.max_extrapolation)
        other.last_pose, other.last_time = self.last_pose.copy(), self.last_time
        if self._motion is not None:
            other._motion = (self._motion[0].copy(), self._motion[1])
        return other

    def forget_motion(self) -> None:
        """Drop the motion estimate (a map (re)initialisation re-sets the translation: the step
        from the frame before it is not a motion)."""
        self._motion = None

    def predict(self, timestamp: float) -> np.ndarray:
        """``T_w_c`` at ``timestamp``: the last relative motion scaled to the elapsed time (so
        frame drops are extrapolated, by at most ``max_extrapolation`` steps), or the last
        pose."""
        if not self.constant_velocity or self._motion is None:
            return self.last_pose
        T_prev_last, dt = self._motion
        if dt <= 0:
            return self.last_pose
        ratio = min((timestamp - self.last_time) / dt, self.max_extrapolation)
        return self.last_pose @ se3_exp(ratio * se3_log(T_prev_last))


@dataclass(frozen=True)
class PredictionBasis:
    """What motion-guided predictions for a later frame are made from, fixed once a frame's
    pose and landmarks are final (before its marginalisation): the tracks ``ids`` at pixels
    ``uv`` of the frame at ``timestamp``, a copy of the motion model, the frame's pose
    ``T_w_old`` and the depths (map units along that camera's z axis; NaN: not a finite
    landmark) of the tracks' landmarks, or of their image neighbours' (see
    :func:`neighbour_depths`; NaN: none). Tracks with a depth are predicted by it, the others
    by the infinite homography."""

    timestamp: float
    model: ConstantVelocityModel
    T_w_old: np.ndarray
    ids: np.ndarray
    uv: np.ndarray
    depths: np.ndarray

    def predict(self, camera, timestamp: float) -> tuple[np.ndarray, np.ndarray]:
        """``(track ids, pixels)`` where the tracks should appear at ``timestamp``."""
        T_new_old = se3_inverse(self.model.predict(timestamp)) @ self.T_w_old
        uv_new, valid = predict_positions(self.uv, camera, T_new_old, self.depths)
        return self.ids[valid], uv_new[valid]


def prediction_basis(model: ConstantVelocityModel, window: SlidingWindow, timestamp: float,
                     ids: np.ndarray, uv: np.ndarray, depth_neighbours: int = 0) -> PredictionBasis | None:
    """The :class:`PredictionBasis` of the tracks ``ids`` at ``uv`` of the frame at
    ``timestamp`` in the current state of the window and motion model; None when there is no
    motion estimate or no track. ``depth_neighbours`` > 0: tracks without a finite landmark get
    the median depth of that many nearest tracks with one (:func:`neighbour_depths`)."""
    if not model.has_motion or not len(ids):
        return None
    T_w_old = model.predict(timestamp)
    inv = window.landmarks.inverse_distances(ids)
    depths = np.full(len(ids), np.nan)
    finite = np.flatnonzero(inv > 0.0)
    depths[finite] = window.landmark_points(ids[finite], se3_inverse(T_w_old))[:, 2]
    depths[inv <= 0.0] = np.inf  # landmarks at infinity: the infinite homography
    if depth_neighbours > 0:
        depths = neighbour_depths(uv, depths, depth_neighbours)
    return PredictionBasis(timestamp, model.copy(), T_w_old, ids.copy(), uv.copy(), depths)


#: :func:`neighbour_depths` needs at least this many tracks with a depth.
MIN_DEPTH_NEIGHBOURS = 3


def neighbour_depths(uv: np.ndarray, depths: np.ndarray, k: int) -> np.ndarray:
    """``depths`` (N,) of the points at pixels ``uv`` (N, 2), with each NaN (no landmark)
    replaced by the median depth of the ``k`` nearest points (pixel distance) with a finite
    positive one: the depth a track without a landmark most likely has on the surface its
    neighbours see. Other values (inf: a landmark at infinity) and points at non-finite pixels
    are kept. Unchanged when fewer than :data:`MIN_DEPTH_NEIGHBOURS` points have a finite
    positive depth.

    Why: most tracks of a frame have no landmark (only keyframes host landmarks), and the
    infinite homography ignores the translation for them. On the 640x480 spiral render (frames
    100-129) the predicted positions were 2.0 / 7.3 px off the tracked ones (median / 90th
    percentile over all tracks), and 8 % of the tracks missed the fine-level guided pass and
    went through the whole pyramid again; with the neighbours' depth 0.22 / 0.43 px and 0.8 %
    (docs/estimator.md, "Depth of tracks without a landmark")."""
    placed = np.isfinite(uv).all(axis=1)
    known = placed & np.isfinite(depths) & (depths > 0.0)
    unknown = np.flatnonzero(placed & np.isnan(depths))
    n_known = int(known.sum())
    if n_known < MIN_DEPTH_NEIGHBOURS or len(unknown) == 0:
        return depths
    out = depths.copy()
    out[unknown] = _median_of_nearest(np.ascontiguousarray(uv[known], dtype=np.float64),
                                      depths[known].astype(np.float64),
                                      np.ascontiguousarray(uv[unknown], dtype=np.float64),
                                      min(int(k), n_known))
    return out


#: Cell size of the grid :func:`_median_of_nearest` searches [px].
_GRID_CELL = 32.0


@numba.njit(cache=True, nogil=True)
def _median_of_nearest(pts: np.ndarray, values: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """For each query (M, 2), the median of ``values`` of its ``k`` nearest ``pts`` (N, 2),
    ``1 <= k <= N``, by exact search on a grid of :data:`_GRID_CELL` px cells, ring by ring
    around the query's cell until no unvisited cell can hold a nearer point
    (:func:`neighbour_depths` of 800 tracks, 500 without a depth: 0.24 ms, with scipy's
    ``cKDTree`` 0.6 ms)."""
    n = pts.shape[0]
    x0 = pts[0, 0]
    y0 = pts[0, 1]
    x1 = x0
    y1 = y0
    for i in range(n):
        x0 = min(x0, pts[i, 0])
        x1 = max(x1, pts[i, 0])
        y0 = min(y0, pts[i, 1])
        y1 = max(y1, pts[i, 1])
    nx = int((x1 - x0) / _GRID_CELL) + 1
    ny = int((y1 - y0) / _GRID_CELL) + 1
    cell = np.empty(n, dtype=np.int64)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(n):
        c = int((pts[i, 1] - y0) / _GRID_CELL) * nx + int((pts[i, 0] - x0) / _GRID_CELL)
        cell[i] = c
        start[c + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    out = np.empty(queries.shape[0])
    best_d = np.empty(k)
    best_v = np.empty(k)
    for q in range(queries.shape[0]):
        x = queries[q, 0]
        y = queries[q, 1]
        cx = min(max(int(math.floor((x - x0) / _GRID_CELL)), 0), nx - 1)
        cy = min(max(int(math.floor((y - y0) / _GRID_CELL)), 0), ny - 1)
        m = 0
        r = 0
        while True:
            for gy in range(cy - r, cy + r + 1):
                if gy < 0 or gy >= ny:
                    continue
                for gx in range(cx - r, cx + r + 1):
                    if gx < 0 or gx >= nx or (abs(gx - cx) < r and abs(gy - cy) < r):
                        continue  # outside the grid, or an inner cell visited before
                    c = gy * nx + gx
                    for oi in range(start[c], start[c + 1]):
                        i = order[oi]
                        dx = pts[i, 0] - x
                        dy = pts[i, 1] - y
                        dist = dx * dx + dy * dy
                        if m == k and dist >= best_d[k - 1]:
                            continue
                        j = m if m < k else k - 1  # insertion into the sorted k best
                        while j > 0 and best_d[j - 1] > dist:
                            best_d[j] = best_d[j - 1]
                            best_v[j] = best_v[j - 1]
                            j -= 1
                        best_d[j] = dist
                        best_v[j] = values[i]
                        if m < k:
                            m += 1
            # the nearest point outside the visited square of cells is at least as far as
            # the nearest of its sides that have cells beyond them
            reach = np.inf
            if cx - r > 0:
                reach = min(reach, x - (x0 + (cx - r) * _GRID_CELL))
            if cx + r + 1 < nx:
                reach = min(reach, x0 + (cx + r + 1) * _GRID_CELL - x)
            if cy - r > 0:
                reach = min(reach, y - (y0 + (cy - r) * _GRID_CELL))
            if cy + r + 1 < ny:
                reach = min(reach, y0 + (cy + r + 1) * _GRID_CELL - y)
            if reach == np.inf or (m == k and best_d[k - 1] <= reach * reach):
                break
            r += 1
        vals = np.sort(best_v[:m])
        out[q] = vals[m // 2] if m % 2 == 1 else 0.5 * (vals[m // 2 - 1] + vals[m // 2])
    return out


def bearing_rotation(camera, predicted_uv: np.ndarray, tracked_uv: np.ndarray,
                     min_pairs: int = 10) -> np.ndarray | None:
    """The rotation ``R`` (3x3) with ``b_tracked ~ R b_predicted`` for the unit bearings of
    predicted and tracked pixels of the same tracks (Kabsch, least squares on the bearings; a
    second pass without the pairs more than 3 median angles off). A camera whose predicted
    pose ``T_w_c`` was off by a rotation only is at ``R_w_c R^T``. None with fewer than
    ``min_pairs`` pairs."""
    b_p, ok_p = camera.unproject(predicted_uv)
    b_t, ok_t = camera.unproject(tracked_uv)
    ok = ok_p & ok_t
    if ok.sum() < min_pairs:
        return None
    return _kabsch_with_outlier_pass(np.ascontiguousarray(b_p[ok]), np.ascontiguousarray(b_t[ok]),
                                     min_pairs)


@numba.njit(cache=True, nogil=True)
def _kabsch_with_outlier_pass(b_p: np.ndarray, b_t: np.ndarray, min_pairs: int) -> np.ndarray:
    """:func:`bearing_rotation` on unit bearings (n, 3): Kabsch, then once more without the
    pairs whose residual angle (sine) exceeds 3 medians, if that leaves ``min_pairs``."""
    n = b_p.shape[0]
    use = np.ones(n, dtype=np.bool_)
    R = kabsch_rotation(b_p, b_t, use)
    angle = np.empty(n)
    for i in range(n):
        q0 = R[0, 0] * b_p[i, 0] + R[0, 1] * b_p[i, 1] + R[0, 2] * b_p[i, 2]
        q1 = R[1, 0] * b_p[i, 0] + R[1, 1] * b_p[i, 1] + R[1, 2] * b_p[i, 2]
        q2 = R[2, 0] * b_p[i, 0] + R[2, 1] * b_p[i, 1] + R[2, 2] * b_p[i, 2]
        c0 = q1 * b_t[i, 2] - q2 * b_t[i, 1]
        c1 = q2 * b_t[i, 0] - q0 * b_t[i, 2]
        c2 = q0 * b_t[i, 1] - q1 * b_t[i, 0]
        angle[i] = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    limit = 3.0 * np.median(angle)
    kept = 0
    for i in range(n):
        use[i] = angle[i] <= limit
        kept += use[i]
    if kept < min_pairs or kept == n:
        return R
    return kabsch_rotation(b_p, b_t, use)
