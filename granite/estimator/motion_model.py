"""Initial guesses for a new frame: the constant-velocity pose and where tracks should appear.

Not in the reference, which starts every frame from the last pose and tracks from the last
positions (``constant_velocity = false``, ``motion_guided_tracking = false``).
"""

from __future__ import annotations

import numpy as np

from granite.backend import SlidingWindow
from granite.geometry import se3_exp, se3_inverse, se3_log
from granite.optical_flow import FrameToFrameOpticalFlow
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


def predicted_track_positions(model: ConstantVelocityModel, flow: FrameToFrameOpticalFlow,
                              window: SlidingWindow, camera, timestamp: float,
                              known: tuple[np.ndarray, np.ndarray] | None = None,
                              ) -> tuple[np.ndarray, np.ndarray] | None:
    """``(track ids, pixels)`` where the frontend's current tracks should appear at
    ``timestamp`` under the predicted pose: tracks of landmarks with d > 0 by their depth, the
    others by the infinite homography. None when there is no motion estimate yet. ``known``:
    ``(ids, inverse distances)`` already read from the window in its current state, used
    when the ids are the frontend's current ones."""
    if not model.has_motion:
        return None
    ids, uv = flow.current_tracks()
    if not len(ids):
        return None
    T_w_old = model.last_pose
    T_old_w = se3_inverse(T_w_old)
    T_new_old = se3_inverse(model.predict(timestamp)) @ T_w_old
    if known is not None and np.array_equal(known[0], ids):
        inv = known[1]
    else:
        inv = window.landmarks.inverse_distances(ids)
    depths = np.full(len(ids), np.nan)
    finite = np.flatnonzero(inv > 0.0)
    depths[finite] = window.landmark_points(ids[finite], T_old_w)[:, 2]
    uv_new, valid = predict_positions(uv, camera, T_new_old, depths)
    return ids[valid], uv_new[valid]
