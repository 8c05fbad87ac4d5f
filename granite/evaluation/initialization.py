"""Initialisation delay: how long after the motion could first give parallax the map exists.

The *parallax onset* is the first processed frame whose ground-truth camera centre is at least
``min_baseline`` (ground-truth units) away from the centre of some earlier processed frame of
the same run: before it, no two frames of the sequence have the baseline a two-view
initialisation needs, whatever the estimator does. With a known scene distance ``rho`` and the
initialisation's parallax threshold ``alpha`` (paper Eq. 8), ``min_baseline = 2 rho tan(alpha /
2)`` (:func:`parallax_baseline`); without one, a small fixed baseline gives "the start of
translation". The delay is counted from the onset to the first frame whose estimator state is
``tracking`` (the frame that initialised the first map), in frames and seconds; None when the
map never initialised (or the sequence never moved enough).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from granite.geometry import interpolate_poses
from granite.trajectory import Trajectory

#: ground-truth baseline (metres in every bundled dataset) that counts as "translation started"
DEFAULT_MIN_BASELINE = 0.05


def parallax_baseline(scene_distance: float, min_parallax_deg: float) -> float:
    """Baseline giving the parallax ``alpha = 2 atan(t / (2 rho))`` of paper Eq. 8."""
    return 2.0 * scene_distance * math.tan(math.radians(min_parallax_deg) / 2.0)


@dataclass(frozen=True)
class InitializationDelay:
    onset_time: float | None  # timestamp of the parallax-onset frame
    onset_frame: int | None  # index (in the processed frames) of that frame
    tracking_time: float | None  # timestamp of the first ``tracking`` frame
    tracking_frame: int | None
    min_baseline: float

    @property
    def frames(self) -> int | None:
        if self.onset_frame is None or self.tracking_frame is None:
            return None
        return max(self.tracking_frame - self.onset_frame, 0)

    @property
    def seconds(self) -> float | None:
        if self.onset_time is None or self.tracking_time is None:
            return None
        return max(self.tracking_time - self.onset_time, 0.0)

    def to_dict(self) -> dict[str, Any]:
        return {
            "init_delay_frames": self.frames,
            "init_delay_s": self.seconds,
            "init_onset_time": self.onset_time,
            "init_tracking_time": self.tracking_time,
            "init_min_baseline": self.min_baseline,
        }


def parallax_onset(timestamps: np.ndarray, gt: Trajectory, min_baseline: float) -> int | None:
    """Index of the first of ``timestamps`` whose ground-truth centre is ``min_baseline`` from
    that of an earlier one (only timestamps inside the ground truth's span count)."""
    ts = np.asarray(timestamps, dtype=np.float64)
    inside = np.flatnonzero((ts >= gt.timestamps[0]) & (ts <= gt.timestamps[-1]))
    if not len(inside):
        return None
    centres = interpolate_poses(gt.timestamps, gt.poses, ts[inside])[:, :3, 3]
    for k in range(1, len(inside)):
        if np.max(np.linalg.norm(centres[:k] - centres[k], axis=1)) >= min_baseline:
            return int(inside[k])
    return None


def parallax_available(timestamps: np.ndarray, gt: Trajectory, scene_distances: np.ndarray,
                       min_parallax_deg: float) -> int | None:
    """Index of the first of ``timestamps`` whose ground-truth centre has, to the centre of an
    earlier one ``j``, the baseline of a parallax of ``min_parallax_deg`` at that frame's scene
    distance ``scene_distances[j]`` (paper Eq. 8, :func:`parallax_baseline`; e.g. the median
    rendered depth): the first frame a two-view initialisation with that threshold could
    accept. Non-finite or non-positive distances never qualify."""
    ts = np.asarray(timestamps, dtype=np.float64)
    rho = np.asarray(scene_distances, dtype=np.float64)
    if rho.shape != ts.shape:
        raise ValueError(f"{len(rho)} scene distances for {len(ts)} timestamps")
    inside = np.flatnonzero((ts >= gt.timestamps[0]) & (ts <= gt.timestamps[-1]))
    if not len(inside):
        return None
    centres = interpolate_poses(gt.timestamps, gt.poses, ts[inside])[:, :3, 3]
    needed = np.array([parallax_baseline(r, min_parallax_deg) if np.isfinite(r) and r > 0
                       else np.inf for r in rho[inside]])
    for k in range(1, len(inside)):
        if np.any(np.linalg.norm(centres[:k] - centres[k], axis=1) >= needed[:k]):
            return int(inside[k])
    return None


def initialization_delay(timestamps, states, gt: Trajectory,
                         min_baseline: float = DEFAULT_MIN_BASELINE) -> InitializationDelay:
    """Delay of the first map initialisation (see the module docstring). ``timestamps`` and
    ``states`` (the ``state`` column of ``diagnostics.csv``) of every processed frame; skipped
    frames are ignored."""
    ts = np.asarray(timestamps, dtype=np.float64)
    keep = np.array([s != "skipped" for s in states], dtype=bool)
    ts, st = ts[keep], [s for s, k in zip(states, keep) if k]
    onset = parallax_onset(ts, gt, min_baseline) if len(ts) else None
    first = next((i for i, s in enumerate(st) if s == "tracking"), None)
    return InitializationDelay(
        None if onset is None else float(ts[onset]), onset,
        None if first is None else float(ts[first]), first, float(min_baseline),
    )
