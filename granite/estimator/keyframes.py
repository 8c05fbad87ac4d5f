"""Keyframe selection by negative entropy (paper Sec. IV-D, Eq. 10).

The negative entropy ``E = ln det(I)`` of the newest pose's Fisher information is compared with
its running average since the last keyframe. A log-determinant can be negative, so the
reference's "drops to or below ``fraction`` of the average" is applied sign-independently:
a drop is ``E <= A - (1 - fraction) * |A|``, which equals ``E <= fraction * A`` for positive
``A`` and still means "lower than the average by the same relative margin" for negative ``A``.

Not in the reference (``[estimator] keyframe_depth_change``, off by default): a keyframe also
when the scene scale changed, i.e. the median depth of the current frame's finite landmarks
(:func:`median_depth`, camera z in the CV convention: z forward) differs from the newest
keyframe's by more than a factor (:func:`depth_ratio_exceeds`); DSO/ORB-SLAM-like. The window
policy's ``marg_depth_change`` uses the same depths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from granite.backend.stereographic import bearings_from_stereo
from granite.geometry import se3_inverse


def entropy_dropped(negative_entropy: float, running_average: float, fraction: float) -> bool:
    """True when ``negative_entropy`` fell below ``fraction`` of ``running_average``."""
    return negative_entropy <= running_average - (1.0 - fraction) * abs(running_average)


@dataclass
class EntropyKeyframeSelector:
    """Stateful keyframe criterion: feed one value per tracked frame, reset at each keyframe.

    ``update`` returns True when a keyframe should be taken: the negative entropy dropped (see
    :func:`entropy_dropped`), fewer than ``min_connected_points`` points are connected, or
    (``invalid_forces_keyframe``) the negative entropy is missing or not finite.
    Entropy drops are only acted on ``min_frames_after_keyframe`` frames after a keyframe.
    """

    fraction: float = 0.995
    min_connected_points: int = 20
    min_frames_after_keyframe: int = 3
    #: a missing or non-finite negative entropy (singular information) forces a keyframe, as
    #: in the reference (False: it is ignored)
    invalid_forces_keyframe: bool = True
    _sum: float = 0.0
    _count: int = 0

    @property
    def frames_since_keyframe(self) -> int:
        """Frames fed to :meth:`update` since the last :meth:`reset`."""
        return self._count

    @property
    def running_average(self) -> float | None:
        return self._sum / self._count if self._count else None

    def reset(self) -> None:
        """Start a new running average (call when a keyframe was inserted)."""
        self._sum, self._count = 0.0, 0

    def update(self, negative_entropy: float, connected_points: int) -> bool:
        if connected_points < self.min_connected_points:
            return True
        if not math.isfinite(negative_entropy):
            return self.invalid_forces_keyframe
        average = self.running_average
        drop = (
            average is not None
            and self._count >= self.min_frames_after_keyframe
            and entropy_dropped(negative_entropy, average, self.fraction)
        )
        self._sum += negative_entropy
        self._count += 1
        return drop


#: fewer finite landmarks in front of the camera and a frame has no median depth
MEDIAN_DEPTH_MIN_POINTS = 5


def median_depth(window, frame_id: int, min_points: int = MEDIAN_DEPTH_MIN_POINTS) -> float | None:
    """Median depth (camera z, map units) of the finite landmarks connected to a window frame
    (observed in it or hosted by it), in that frame's camera at the current estimate; None
    with fewer than ``min_points`` finite landmarks in front of the camera. A ratio of two
    such medians is invariant to a scaling of the world (the scene scale seen by the camera)."""
    db = window.landmarks
    ids = db.observed_in(frame_id) | db.hosted_by(frame_id)
    if len(ids) < min_points:
        return None
    lms = [lm for lm in db.landmarks_of(list(ids)) if lm.inv_dist > 0.0]
    if len(lms) < min_points:
        return None
    d = np.fromiter([lm.inv_dist for lm in lms], dtype=np.float64, count=len(lms))
    hosts = np.fromiter([lm.host_frame_id for lm in lms], dtype=np.int64, count=len(lms))
    p_h = bearings_from_stereo(np.array([lm.s for lm in lms], dtype=np.float64)) / d[:, None]
    T_c_w = se3_inverse(window.pose(frame_id))
    z = np.empty(len(lms))
    for host in np.unique(hosts).tolist():  # only the depth row of T_c_h
        mask = hosts == host
        row = (T_c_w @ window.pose(host))[2]
        z[mask] = p_h[mask] @ row[:3] + row[3]
    z = z[z > 0.0]
    return float(np.median(z)) if len(z) >= min_points else None


def depth_ratio_exceeds(depth: float | None, reference_depth: float | None, change: float) -> bool:
    """True when the two median depths differ by more than the factor ``1 + change`` either way
    (``|ln(depth / reference_depth)| > ln(1 + change)``); False when ``change`` is 0 (off) or a
    depth is undefined."""
    if change <= 0.0 or depth is None or reference_depth is None:
        return False
    if not (depth > 0.0 and reference_depth > 0.0):
        return False
    return abs(math.log(depth / reference_depth)) > math.log1p(change)
