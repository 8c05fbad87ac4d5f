"""Initial guesses for a new frame: the constant-velocity pose and where tracks should appear.

Not in the reference, which starts every frame from the last pose and tracks from the last
positions (``constant_velocity = false``, ``motion_guided_tracking = false``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from granite.backend import SlidingWindow
from granite.geometry import se3_exp, se3_inverse, se3_log
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
    neighbours see. Other values (inf: a landmark at infinity) are kept. Unchanged when fewer
    than :data:`MIN_DEPTH_NEIGHBOURS` points have a finite positive depth.

    Why: most tracks of a frame have no landmark (only keyframes host landmarks), and the
    infinite homography ignores the translation for them. On the 640x480 spiral render (frames
    100-129) the predicted positions were 2.0 / 7.3 px off the tracked ones (median / 90th
    percentile over all tracks), and 8 % of the tracks missed the fine-level guided pass and
    went through the whole pyramid again; with the neighbours' depth 0.22 / 0.43 px and 0.1 %
    (docs/estimator.md, "Depth of tracks without a landmark")."""
    known = np.isfinite(depths) & (depths > 0.0)
    unknown = np.flatnonzero(np.isnan(depths))
    n_known = int(known.sum())
    if n_known < MIN_DEPTH_NEIGHBOURS or len(unknown) == 0:
        return depths
    from scipy.spatial import cKDTree

    k = min(int(k), n_known)
    known_depths = depths[known]
    _, nearest = cKDTree(uv[known]).query(uv[unknown], k=k)
    out = depths.copy()
    out[unknown] = np.median(known_depths[nearest.reshape(len(unknown), k)], axis=1)
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
def _kabsch_rotation(b_p: np.ndarray, b_t: np.ndarray, use: np.ndarray) -> np.ndarray:
    """``R`` minimising ``sum |b_t - R b_p|^2`` over the pairs ``use`` (proper rotation)."""
    M = np.zeros((3, 3))
    for i in range(b_p.shape[0]):
        if use[i]:
            for r in range(3):
                for c in range(3):
                    M[r, c] += b_t[i, r] * b_p[i, c]
    U, _, Vt = np.linalg.svd(M)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    return U @ D @ Vt


@numba.njit(cache=True, nogil=True)
def _kabsch_with_outlier_pass(b_p: np.ndarray, b_t: np.ndarray, min_pairs: int) -> np.ndarray:
    """:func:`bearing_rotation` on unit bearings (n, 3): Kabsch, then once more without the
    pairs whose residual angle (sine) exceeds 3 medians, if that leaves ``min_pairs``."""
    n = b_p.shape[0]
    use = np.ones(n, dtype=np.bool_)
    R = _kabsch_rotation(b_p, b_t, use)
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
    return _kabsch_rotation(b_p, b_t, use)
