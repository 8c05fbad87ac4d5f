"""Predictions corrected by a few tracks tracked first: probe tracking (ours).

The estimator predicts every track's position in the new frame from the constant-velocity
camera motion (motion-guided tracking, :mod:`granite.optical_flow.prediction`). In fast turns
that motion is off, and so is every prediction, by about the same image motion: on the
640x480 ``aggressive`` flight the predictions were a median 8-16 px off (on the creation level
of each patch) while the spiral's were 0.2 px off, so most tracks missed the fine guided pass and
were tracked again through the whole pyramid. The error of the predictions is mostly one image
transformation (a rotation error of the camera moves the image by a homography, and the ground
seen from above by nearly one), so a few tracks found first tell it: their predicted and
tracked positions give a homography (RANSAC), and the other tracks start from their corrected
predictions. On the captured frames of that flight the median error fell to 0.2-0.3 px.

Positions are level-0 pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

#: RANSAC inlier threshold [level-0 px] of the correction, and the least probes that must
#: agree with it (number, share of the probes found).
THRESHOLD_PX = 2.0
MIN_INLIERS = 8
MIN_INLIER_SHARE = 0.5


def probe_indices(guess: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` indices of tracks with a prediction (finite rows of ``guess`` (N, 2)),
    evenly spaced over them (the tracks are in creation order, so the probes come from every
    age and, as detection fills the image cell by cell, from all over it); empty when fewer
    than ``MIN_INLIERS`` tracks have a prediction or ``count`` is 0."""
    with_guess = np.flatnonzero(np.isfinite(guess).all(axis=1))
    if count <= 0 or len(with_guess) < MIN_INLIERS:
        return np.zeros(0, dtype=np.int64)
    if len(with_guess) <= count:
        return with_guess
    return with_guess[np.linspace(0, len(with_guess) - 1, count).round().astype(np.int64)]


def prediction_correction(predicted: np.ndarray, tracked: np.ndarray) -> np.ndarray | None:
    """The homography (3, 3) taking the probes' predicted positions (M, 2) to where they were
    tracked (M, 2), RANSAC with ``THRESHOLD_PX`` (OpenCV, deterministic), or None when fewer
    than ``MIN_INLIERS`` (or ``MIN_INLIER_SHARE`` of the probes) agree with it."""
    if len(predicted) < MIN_INLIERS:
        return None
    H, mask = cv2.findHomography(np.asarray(predicted, dtype=np.float64),
                                 np.asarray(tracked, dtype=np.float64), cv2.RANSAC, THRESHOLD_PX)
    if H is None or mask is None or not np.all(np.isfinite(H)):
        return None
    inliers = int(mask.sum())
    if inliers < MIN_INLIERS or inliers < MIN_INLIER_SHARE * len(predicted):
        return None
    return H


def corrected_guess(points: np.ndarray, guess: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Displacements (N, 2) from ``points`` (N, 2) to their predicted positions
    ``points + guess`` mapped by ``H``; rows without a prediction, or mapped to infinity, keep
    ``guess``."""
    predicted = points + guess
    p = np.c_[predicted, np.ones(len(points))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        q = p[:, :2] / p[:, 2:3]
    ok = np.isfinite(q).all(axis=1) & (np.abs(p[:, 2]) > 1e-12)
    out = guess.copy()
    out[ok] = q[ok] - points[ok]
    return out
