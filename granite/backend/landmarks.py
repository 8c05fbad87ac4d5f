"""Landmarks (bearing + inverse distance in a host keyframe) and their observations.

A landmark ``l`` is hosted by a keyframe ``h``: its homogeneous position in the host camera
frame is ``[b, d]`` with ``b`` a unit bearing (3,) and ``d >= 0`` the inverse distance
[1 / map unit]; the Euclidean point is ``b / d`` and ``d = 0`` is a point at infinity (paper
Sec. IV-B). In any target frame ``t`` the point is, up to a positive scale,
``p_t = R_t_h b + t_t_h d`` (valid at ``d = 0``).

The bearing is stored minimally as its stereographic projection ``s`` (2,) from the pole
``(0, 0, -1)``: ``s = (b_x, b_y) / (1 + b_z)``, ``b = (2 s, 1 - |s|^2) / (1 + |s|^2)``; it is
updated additively (``s <- s + ds``). It is singular only for a bearing pointing exactly
backwards (``b_z = -1``), which no camera observes.

Observations ``z`` are pixel coordinates (u, v) with the pyramid level ``c`` the feature was
created on (weight ``2**-c``, paper Eq. 7).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numba
import numpy as np


@numba.njit(cache=True)
def bearing_from_stereo_into(x: float, y: float, b: np.ndarray, J: np.ndarray) -> None:
    """Write the unit bearing ``b`` (3,) of the stereographic vector ``(x, y)`` and its Jacobian
    ``db/ds`` (3,2) into preallocated arrays (allocation-free, for kernels)."""
    n2 = x * x + y * y
    inv = 1.0 / (1.0 + n2)
    b[0] = 2.0 * x * inv
    b[1] = 2.0 * y * inv
    b[2] = (1.0 - n2) * inv
    inv2 = inv * inv
    J[0, 0] = 2.0 * inv - 4.0 * x * x * inv2
    J[0, 1] = -4.0 * x * y * inv2
    J[1, 0] = J[0, 1]
    J[1, 1] = 2.0 * inv - 4.0 * y * y * inv2
    J[2, 0] = -4.0 * x * inv2
    J[2, 1] = -4.0 * y * inv2


@numba.njit(cache=True)
def bearing_from_stereo(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearing ``b`` (3,) of a stereographic 2-vector and its Jacobian ``db/ds`` (3,2)."""
    b = np.empty(3)
    J = np.empty((3, 2))
    bearing_from_stereo_into(s[0], s[1], b, J)
    return b, J


def stereo_from_bearing(bearing: np.ndarray) -> np.ndarray:
    """Stereographic 2-vector(s) of bearing(s) (..., 3); the input is normalised first."""
    b = np.asarray(bearing, dtype=np.float64)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    if np.any(b[..., 2] <= -1.0 + 1e-9):
        raise ValueError("bearing points backwards (b_z = -1): no stereographic parameter")
    return b[..., :2] / (1.0 + b[..., 2:3])


def bearings_from_stereo(s: np.ndarray) -> np.ndarray:
    """Vectorised inverse of :func:`stereo_from_bearing`: (..., 2) -> unit bearings (..., 3)."""
    s = np.asarray(s, dtype=np.float64)
    n2 = np.sum(s * s, axis=-1, keepdims=True)
    return np.concatenate([2.0 * s, 1.0 - n2], axis=-1) / (1.0 + n2)


@dataclasses.dataclass
class Landmark:
    """State of one landmark: host keyframe id, stereographic bearing ``s`` (2,) in the host
    camera frame and inverse distance ``inv_dist`` (``>= 0``, 0 = at infinity)."""

    host_frame_id: int
    s: np.ndarray
    inv_dist: float

    @property
    def bearing(self) -> np.ndarray:
        """Unit bearing (3,) in the host camera frame."""
        return bearings_from_stereo(self.s)

    def point_in_host(self) -> np.ndarray:
        """Euclidean point (3,) in the host frame; ``inf`` components when ``inv_dist == 0``."""
        b = self.bearing
        if self.inv_dist <= 0.0:
            return np.where(b == 0.0, 0.0, np.sign(b) * np.inf)
        return b / self.inv_dist


@dataclasses.dataclass(frozen=True)
class Observation:
    """A landmark seen in a frame at pixel ``uv`` (2,), tracked from pyramid level ``level``."""

    uv: np.ndarray
    level: int


@dataclasses.dataclass
class PackedObservations:
    """Flat arrays of (a subset of) the database for the numba kernels.

    Landmark rows follow ``landmark_ids``; observations are grouped by landmark,
    ``lm_ptr[i]:lm_ptr[i+1]`` being the observations of landmark ``i``. Pose indices refer to
    the ``frame_ids`` given to :meth:`LandmarkDatabase.pack`.
    """

    landmark_ids: np.ndarray  # (M,) int64
    lm_host: np.ndarray  # (M,) int64 pose index of the host
    lm_s: np.ndarray  # (M, 2) stereographic bearings
    lm_d: np.ndarray  # (M,) inverse distances
    lm_ptr: np.ndarray  # (M+1,) int64
    obs_lm: np.ndarray  # (N,) int64 landmark row
    obs_tgt: np.ndarray  # (N,) int64 pose index of the observing frame
    obs_uv: np.ndarray  # (N, 2)
    obs_level: np.ndarray  # (N,) int64

    @property
    def num_landmarks(self) -> int:
        return int(self.landmark_ids.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.obs_lm.shape[0])


class LandmarkDatabase:
    """Landmarks and observations, indexed per landmark, per observing frame and per host.

    Ids are arbitrary integers chosen by the caller (the frontend's keypoint ids and frame
    ids). Every landmark's host must be a frame of the window; the window enforces it.
    """

    def __init__(self) -> None:
        self._landmarks: dict[int, Landmark] = {}
        self._obs: dict[int, dict[int, Observation]] = {}
        self._obs_in_frame: dict[int, set[int]] = {}
        self._hosted: dict[int, set[int]] = {}

    # ----------------------------------------------------------------- landmarks
    def __contains__(self, landmark_id: int) -> bool:
        return landmark_id in self._landmarks

    def __len__(self) -> int:
        return len(self._landmarks)

    @property
    def landmark_ids(self) -> list[int]:
        return list(self._landmarks)

    def landmark(self, landmark_id: int) -> Landmark:
        return self._landmarks[landmark_id]

    def add_landmark(self, landmark_id: int, host_frame_id: int, bearing: np.ndarray,
                     inv_dist: float) -> None:
        """Add a landmark with unit (or any non-zero) bearing (3,) in the host camera frame."""
        if landmark_id in self._landmarks:
            raise ValueError(f"landmark {landmark_id} already exists")
        if not np.isfinite(inv_dist) or inv_dist < 0.0:
            raise ValueError(f"landmark {landmark_id}: inverse distance must be >= 0, "
                             f"got {inv_dist}")
        s = stereo_from_bearing(np.asarray(bearing, dtype=np.float64).reshape(3))
        self._landmarks[landmark_id] = Landmark(int(host_frame_id), s, float(inv_dist))
        self._obs[landmark_id] = {}
        self._hosted.setdefault(int(host_frame_id), set()).add(landmark_id)

    def remove_landmark(self, landmark_id: int) -> None:
        lm = self._landmarks.pop(landmark_id)
        for frame_id in self._obs.pop(landmark_id):
            self._obs_in_frame[frame_id].discard(landmark_id)
        self._hosted[lm.host_frame_id].discard(landmark_id)

    def hosted_by(self, frame_id: int) -> set[int]:
        """Ids of the landmarks hosted by a frame."""
        return set(self._hosted.get(frame_id, ()))

    # -------------------------------------------------------------- observations
    def add_observation(self, landmark_id: int, frame_id: int, uv: np.ndarray,
                        level: int = 0) -> None:
        """Add (or replace) the observation of a landmark in a frame."""
        if landmark_id not in self._landmarks:
            raise KeyError(f"observation of unknown landmark {landmark_id}")
        uv = np.asarray(uv, dtype=np.float64).reshape(2).copy()
        if not np.all(np.isfinite(uv)):
            raise ValueError(f"observation of landmark {landmark_id} in frame {frame_id} "
                             "is not finite")
        self._obs[landmark_id][int(frame_id)] = Observation(uv, int(level))
        self._obs_in_frame.setdefault(int(frame_id), set()).add(landmark_id)

    def remove_observation(self, landmark_id: int, frame_id: int) -> None:
        del self._obs[landmark_id][frame_id]
        self._obs_in_frame[frame_id].discard(landmark_id)

    def observations(self, landmark_id: int) -> dict[int, Observation]:
        """Observations of a landmark: frame id -> observation (a copy of the mapping)."""
        return dict(self._obs[landmark_id])

    def observed_in(self, frame_id: int) -> set[int]:
        """Ids of the landmarks observed in a frame."""
        return set(self._obs_in_frame.get(frame_id, ()))

    def remove_frame(self, frame_id: int) -> list[int]:
        """Drop all observations made in a frame and all landmarks it hosts; returns the ids
        of the removed landmarks."""
        for lm_id in list(self._obs_in_frame.get(frame_id, ())):
            self.remove_observation(lm_id, frame_id)
        self._obs_in_frame.pop(frame_id, None)
        removed = sorted(self._hosted.get(frame_id, ()))
        for lm_id in removed:
            self.remove_landmark(lm_id)
        self._hosted.pop(frame_id, None)
        return removed

    @property
    def num_observations(self) -> int:
        return sum(len(o) for o in self._obs.values())

    # ------------------------------------------------------------------- packing
    def pack(self, frame_index: dict[int, int], landmark_ids: Iterable[int] | None = None,
             target_filter: set[int] | None = None) -> PackedObservations:
        """Flatten landmarks and observations into arrays for the kernels.

        Args:
            frame_index: frame id -> pose index; observations in frames not in it are skipped.
            landmark_ids: landmarks to include (default: all, in id order).
            target_filter: if given, only observations made in these frames are included.
        """
        ids = sorted(self._landmarks) if landmark_ids is None else list(landmark_ids)
        m = len(ids)
        lm_host = np.empty(m, dtype=np.int64)
        lm_s = np.empty((m, 2))
        lm_d = np.empty(m)
        lm_ptr = np.zeros(m + 1, dtype=np.int64)
        obs_tgt: list[int] = []
        obs_uv: list[np.ndarray] = []
        obs_level: list[int] = []
        for i, lm_id in enumerate(ids):
            lm = self._landmarks[lm_id]
            lm_host[i] = frame_index[lm.host_frame_id]
            lm_s[i] = lm.s
            lm_d[i] = lm.inv_dist
            count = 0
            for frame_id, ob in self._obs[lm_id].items():
                if frame_id not in frame_index:
                    continue
                if target_filter is not None and frame_id not in target_filter:
                    continue
                obs_tgt.append(frame_index[frame_id])
                obs_uv.append(ob.uv)
                obs_level.append(ob.level)
                count += 1
            lm_ptr[i + 1] = lm_ptr[i] + count
        n = int(lm_ptr[-1])
        return PackedObservations(
            landmark_ids=np.asarray(ids, dtype=np.int64),
            lm_host=lm_host,
            lm_s=lm_s,
            lm_d=lm_d,
            lm_ptr=lm_ptr,
            obs_lm=np.repeat(np.arange(m, dtype=np.int64), np.diff(lm_ptr)),
            obs_tgt=np.asarray(obs_tgt, dtype=np.int64).reshape(n),
            obs_uv=np.asarray(obs_uv, dtype=np.float64).reshape(n, 2),
            obs_level=np.asarray(obs_level, dtype=np.int64).reshape(n),
        )

    def unpack_states(self, packed: PackedObservations) -> None:
        """Write the landmark states (``lm_s``, ``lm_d``) of a packed problem back."""
        for i, lm_id in enumerate(packed.landmark_ids.tolist()):
            lm = self._landmarks[lm_id]
            lm.s = packed.lm_s[i].copy()
            lm.inv_dist = float(packed.lm_d[i])
