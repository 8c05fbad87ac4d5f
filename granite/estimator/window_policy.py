"""Which frames leave the sliding window after each frame (the reference's window policy).

Non-keyframes older than the newest ``max_frames`` frames leave. If more than
``max_keyframes`` keyframes remain, one keyframe is marginalised: the oldest one with fewer than
``marg_seen_fraction`` of its hosted landmarks seen in the newest frame, otherwise the one with
the largest DSO distance score ``sqrt(|t_k - t_last|) * sum_j 1 / (|t_k - t_j| + eps)``
(``t`` the camera centres of the keyframes, ``t_last`` the newest keyframe's, ``eps =
marg_distance_epsilon``). The newest ``max_frames`` frames, and the keyframes the caller asks to keep, are never chosen.

Two rules of ours (both off by default, as in the reference). With ``marg_max_keyframe_age >
0`` the window has a time horizon: whenever it holds more than ``AGE_MIN_KEYFRAMES`` keyframes
and its oldest (by timestamp; not a recent frame, not kept) is older than that many seconds
relative to the newest frame, that keyframe leaves, one per frame, whether or not the window
is full. When the window is full, with ``marg_depth_change > 0`` the keyframe whose median
landmark depth (:func:`granite.estimator.keyframes.median_depth`) differs most from the newest
frame's leaves first, when it differs by more than the factor ``1 + marg_depth_change`` (a
keyframe that saw the scene at another scale).

Departures from the reference (granite's ``KeypointVoEstimator::marginalize``): it takes the
keyframe with the *smallest* score (DSO, which the score comes from, removes the largest: the
keyframe close to others and far from the newest); its score sums over all keyframes but the
two newest, including ``j = k`` (a constant ``1 / eps``); and its "lost most landmarks" test
divides two integers, so it fires for any keyframe that has lost at least one landmark
connection.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from granite.backend import BackendConfig, SlidingWindow
from granite.estimator.keyframes import median_depth

#: the keyframe-age rule never leaves fewer keyframes in the window (the scale-drift indicator
#: needs 3)
AGE_MIN_KEYFRAMES = 3


def frames_to_marginalize(window: SlidingWindow, config: BackendConfig,
                          keep: frozenset[int] | set[int] = frozenset(),
                          timestamps: Mapping[int, float] | None = None) -> list[int]:
    """Frame ids to pass to :meth:`SlidingWindow.marginalize` (see the module docstring);
    window size and rule constants come from ``config`` (the ``[backend]`` table). Keyframes
    in ``keep`` are never chosen (the estimator keeps its map-initialisation reference while no
    map exists). ``timestamps`` (frame id -> seconds, every window frame) is needed only by
    ``marg_max_keyframe_age``."""
    ids = window.frame_ids
    if not ids:
        return []
    recent = set(ids[-config.max_frames:])
    out = [f for f in ids if f not in recent and not window.is_keyframe(f)]
    kfs = [f for f in window.keyframe_ids if f not in out]
    if config.marg_max_keyframe_age > 0.0 and timestamps is not None and len(kfs) > AGE_MIN_KEYFRAMES:
        candidates = [f for f in kfs if f not in recent and f not in keep]
        if candidates:
            oldest = min(candidates, key=lambda f: timestamps[f])
            if timestamps[ids[-1]] - timestamps[oldest] > config.marg_max_keyframe_age:
                return out + [oldest]
    if len(kfs) <= config.max_keyframes:
        return out
    db = window.landmarks
    seen = db.observed_in(ids[-1])
    candidates = [f for f in kfs if f not in recent and f not in keep]
    if config.marg_depth_change > 0.0 and candidates:
        far = _farthest_in_depth(window, ids[-1], candidates, config.marg_depth_change)
        if far is not None:
            return out + [far]
    for f in candidates:
        hosted = db.hosted_by(f)
        if not hosted or len(hosted & seen) < config.marg_seen_fraction * len(hosted):
            return out + [f]
    centres = {f: window.pose(f)[:3, 3] for f in kfs}
    t_last = centres[kfs[-1]]
    best, best_score = None, -math.inf
    for f in candidates:
        t_f = centres[f]
        denom = sum(1.0 / (np.linalg.norm(t_f - centres[g]) + config.marg_distance_epsilon)
                    for g in kfs if g != f)
        score = math.sqrt(np.linalg.norm(t_f - t_last)) * denom
        if score > best_score:
            best, best_score = f, score
    return out + ([best] if best is not None else [])


def _farthest_in_depth(window: SlidingWindow, newest: int, candidates: list[int],
                       change: float) -> int | None:
    """The candidate keyframe whose median depth differs most from the newest frame's, if by
    more than the factor ``1 + change`` (log ratio); None otherwise or without depths."""
    d_new = median_depth(window, newest)
    if d_new is None:
        return None
    best, best_ratio = None, math.log1p(change)
    for f in candidates:
        d = median_depth(window, f)
        if d is None:
            continue
        ratio = abs(math.log(d / d_new))
        if ratio > best_ratio:
            best, best_ratio = f, ratio
    return best
