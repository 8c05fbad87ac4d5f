"""The image motion between two frames as one homography from ORB matches (OpenCV): the guess
for the tracks that the frame-to-frame tracking lost all at once.

After a burst of dropped frames the tracks' predicted positions (the constant-velocity motion,
or zero motion) can be far off: across six dropped frames of the ``aggressive`` flight the
camera turned 12 degrees, the constant-velocity guess was 35 degrees off and the image moved
65 px, and none of the tracks was found again (docs/estimator.md). Features matched by
appearance over the whole image do not need a guess. Over terrain seen from above, one homography (the ground plane's,
rotation included) predicts every track within a few pixels, and the patch tracker then finds
them from there (:meth:`granite.optical_flow.FrameToFrameOpticalFlow.begin`, ours, option
``[optical_flow] global_retry_min_lost``).
"""

from __future__ import annotations

import cv2
import numpy as np

#: ORB features per image, their patch size (the detection border) and Lowe's ratio.
_FEATURES = 1000
_PATCH = 19
_RATIO = 0.8
#: RANSAC inlier threshold [level-0 px] and the least inliers (number, share of the matches)
#: for a homography to be used.
_THRESHOLD_PX = 3.0
_MIN_INLIERS = 20
_MIN_INLIER_SHARE = 0.4


def image_homography(image_a: np.ndarray, image_b: np.ndarray) -> np.ndarray | None:
    """``H`` (3, 3) mapping level-0 pixels of 8-bit image A to image B (OpenCV ORB, ratio-test
    matches, RANSAC homography; deterministic), or None when fewer than ``_MIN_INLIERS``
    matches (or less than ``_MIN_INLIER_SHARE`` of them) agree."""
    orb = cv2.ORB_create(nfeatures=_FEATURES, edgeThreshold=_PATCH, patchSize=_PATCH)
    kp_a, des_a = orb.detectAndCompute(image_a, None)
    kp_b, des_b = orb.detectAndCompute(image_b, None)
    if des_a is None or des_b is None or len(kp_a) < 2 or len(kp_b) < 2:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(des_a, des_b, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < _RATIO * p[1].distance]
    if len(good) < _MIN_INLIERS:
        return None
    pa = np.float32([kp_a[m.queryIdx].pt for m in good])
    pb = np.float32([kp_b[m.trainIdx].pt for m in good])
    H, mask = cv2.findHomography(pa, pb, cv2.RANSAC, _THRESHOLD_PX)
    if H is None or mask is None:
        return None
    inliers = int(mask.sum())
    if inliers < _MIN_INLIERS or inliers < _MIN_INLIER_SHARE * len(good) or not np.all(np.isfinite(H)):
        return None
    return H


def homography_guess(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Displacements (N, 2) that ``H`` predicts for level-0 ``points`` (N, 2); NaN rows where
    a point maps to infinity."""
    p = np.c_[points, np.ones(len(points))] @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        q = p[:, :2] / p[:, 2:3]
    q[~(np.abs(p[:, 2]) > 1e-12)] = np.nan
    return q - points
