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
import math
import operator
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


def _uv_pair(uv) -> tuple[float, float]:
    """``(u, v)`` as Python floats from a (2,) array (fast path) or anything of 2 elements."""
    if type(uv) is np.ndarray and uv.shape == (2,):
        return float(uv[0]), float(uv[1])
    a = np.asarray(uv, dtype=np.float64).reshape(2)
    return float(a[0]), float(a[1])


class LandmarkDatabase:
    """Landmarks and observations, indexed per landmark, per observing frame and per host.

    Ids are arbitrary integers chosen by the caller (the frontend's keypoint ids and frame
    ids). Every landmark's host must be a frame of the window; the window enforces it.

    Storage (for fast packing): observations live in growable flat arrays ("slots": landmark
    id, frame id, uv, level, alive flag) in insertion order; ``landmark -> {frame -> slot}``
    and ``frame -> {landmarks}`` index them. New observations are first appended to Python
    lists and moved into the arrays in bulk when the arrays are needed. Removed slots are
    marked dead and compacted away (order preserving) once they outnumber the live ones.
    Within a landmark, slot order is the order in which its observations were added (a
    replaced observation keeps its place), which is the order :meth:`pack` uses.
    """

    _MIN_COMPACT = 4096  # dead slots tolerated before compaction

    def __init__(self) -> None:
        self._landmarks: dict[int, Landmark] = {}
        self._obs: dict[int, dict[int, int]] = {}  # landmark -> {frame -> slot}
        self._obs_in_frame: dict[int, set[int]] = {}
        self._hosted: dict[int, set[int]] = {}
        cap = 1024
        self._o_lm = np.empty(cap, dtype=np.int64)
        self._o_frame = np.empty(cap, dtype=np.int64)
        self._o_uv = np.empty((cap, 2))
        self._o_level = np.empty(cap, dtype=np.int64)
        self._o_alive = np.zeros(cap, dtype=bool)
        self._n_flushed = 0  # slots [0, _n_flushed) are in the arrays
        self._p_lm: list[int] = []  # pending slots [_n_flushed, _n_flushed + len(_p_lm))
        self._p_frame: list[int] = []
        self._p_u: list[float] = []
        self._p_v: list[float] = []
        self._p_level: list[int] = []
        self._n_alive = 0
        self._version = 0  # bumped on every change of landmarks / observations (not states)
        self._pack_cache: tuple | None = None
        self._s_store: tuple[list[np.ndarray], np.ndarray] | None = None

    def __getstate__(self) -> dict:
        """Pickle / deepcopy without the caches (the bearing store relies on object identity
        of row views, which copies do not preserve)."""
        state = self.__dict__.copy()
        state["_pack_cache"] = None
        state["_s_store"] = None
        return state

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
        self._version += 1

    def remove_landmark(self, landmark_id: int) -> None:
        lm = self._landmarks.pop(landmark_id)
        for frame_id, slot in self._obs.pop(landmark_id).items():
            self._obs_in_frame[frame_id].discard(landmark_id)
            self._kill(slot)
        self._hosted[lm.host_frame_id].discard(landmark_id)
        self._version += 1

    def hosted_by(self, frame_id: int) -> set[int]:
        """Ids of the landmarks hosted by a frame."""
        return set(self._hosted.get(frame_id, ()))

    def num_connected(self, frame_id: int) -> tuple[int, int]:
        """``(finite, infinite)``: landmarks observed in a frame with ``d > 0`` and otherwise."""
        ids = self._obs_in_frame.get(frame_id)
        if not ids:
            return 0, 0
        lms = self._landmarks
        finite = sum([lms[i].inv_dist > 0.0 for i in ids])
        return finite, len(ids) - finite

    def inverse_distances(self, landmark_ids) -> np.ndarray:
        """Inverse distances (n,) of the given ids, NaN for ids that are not landmarks."""
        lms = self._landmarks
        nan = math.nan
        out: list[float] = []
        for i in np.asarray(landmark_ids, dtype=np.int64).reshape(-1).tolist():
            lm = lms.get(i)
            out.append(nan if lm is None else lm.inv_dist)
        return np.array(out, dtype=np.float64)

    # -------------------------------------------------------------- observations
    def add_observation(self, landmark_id: int, frame_id: int, uv: np.ndarray,
                        level: int = 0) -> None:
        """Add (or replace) the observation of a landmark in a frame."""
        obs = self._obs.get(landmark_id)
        if obs is None:
            raise KeyError(f"observation of unknown landmark {landmark_id}")
        u, v = _uv_pair(uv)
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ValueError(f"observation of landmark {landmark_id} in frame {frame_id} "
                             "is not finite")
        frame_id = int(frame_id)
        level = int(level)
        slot = obs.get(frame_id)
        if slot is None:
            obs[frame_id] = self._n_flushed + len(self._p_lm)
            self._p_lm.append(landmark_id)
            self._p_frame.append(frame_id)
            self._p_u.append(u)
            self._p_v.append(v)
            self._p_level.append(level)
            self._n_alive += 1
            in_frame = self._obs_in_frame.get(frame_id)
            if in_frame is None:
                in_frame = self._obs_in_frame[frame_id] = set()
            in_frame.add(landmark_id)
        elif slot >= self._n_flushed:
            i = slot - self._n_flushed
            self._p_u[i] = u
            self._p_v[i] = v
            self._p_level[i] = level
        else:
            self._o_uv[slot, 0] = u
            self._o_uv[slot, 1] = v
            self._o_level[slot] = level
        self._version += 1

    def add_observations(self, frame_id: int, landmark_ids, uvs: np.ndarray,
                         levels=None, skip_unknown: bool = False) -> int:
        """Add (or replace) observations made in one frame: ``landmark_ids`` (n,), pixel
        positions ``uvs`` (n, 2), pyramid levels (n,) (default 0). With ``skip_unknown`` ids
        that are not landmarks are ignored, otherwise they raise ``KeyError``. The batch is
        validated before anything is added. Returns the number of observations added."""
        fid = int(frame_id)
        ids = np.asarray(landmark_ids, dtype=np.int64).reshape(-1)
        uvs = np.asarray(uvs, dtype=np.float64).reshape(-1, 2)
        n = ids.shape[0]
        lv = np.zeros(n, dtype=np.int64) if levels is None else \
            np.asarray(levels, dtype=np.int64).reshape(-1)
        if uvs.shape[0] != n or lv.shape[0] != n:
            raise ValueError("add_observations: landmark_ids, uvs and levels differ in length")
        obs_dicts = self._obs
        ids_list = ids.tolist()
        known = [k for k, i in enumerate(ids_list) if i in obs_dicts]
        if len(known) != n:
            if not skip_unknown:
                raise KeyError("observation of unknown landmark "
                               f"{next(i for i in ids_list if i not in obs_dicts)}")
            ids_list = [ids_list[k] for k in known]
            ids, uvs, lv = ids[known], uvs[known], lv[known]
            n = len(known)
        if n == 0:
            return 0
        if not np.all(np.isfinite(uvs)):
            raise ValueError(f"observations in frame {fid} are not finite")
        self._flush()
        base = self._n_flushed
        nxt = base
        new_rows: list[int] = []
        replaced: list[tuple[int, int]] = []
        for k, lm_id in enumerate(ids_list):
            d = obs_dicts[lm_id]
            slot = d.get(fid)
            if slot is None:
                d[fid] = nxt
                nxt += 1
                new_rows.append(k)
            else:
                replaced.append((slot, k))
        in_frame = self._obs_in_frame.get(fid)
        if in_frame is None:
            in_frame = self._obs_in_frame[fid] = set()
        in_frame.update(ids_list)
        if nxt > base:
            self._reserve(nxt)
            sel = slice(None) if nxt - base == n else np.asarray(new_rows, dtype=np.int64)
            self._o_lm[base:nxt] = ids[sel]
            self._o_frame[base:nxt] = fid
            self._o_uv[base:nxt] = uvs[sel]
            self._o_level[base:nxt] = lv[sel]
            self._o_alive[base:nxt] = True
            self._n_flushed = nxt
            self._n_alive += nxt - base
        for slot, k in replaced:
            self._o_uv[slot] = uvs[k]
            self._o_level[slot] = lv[k]
        self._version += 1
        return n

    def remove_observation(self, landmark_id: int, frame_id: int) -> None:
        slot = self._obs[landmark_id].pop(frame_id)
        self._obs_in_frame[frame_id].discard(landmark_id)
        self._kill(slot)
        self._version += 1

    def observations(self, landmark_id: int) -> dict[int, Observation]:
        """Observations of a landmark: frame id -> observation (a copy of the mapping)."""
        return {f: self._observation_at(s) for f, s in self._obs[landmark_id].items()}

    def observation(self, landmark_id: int, frame_id: int) -> Observation:
        """The observation of a landmark in a frame (``KeyError`` if there is none)."""
        return self._observation_at(self._obs[landmark_id][frame_id])

    def has_observation(self, landmark_id: int, frame_id: int) -> bool:
        obs = self._obs.get(landmark_id)
        return obs is not None and frame_id in obs

    def observed_in(self, frame_id: int) -> set[int]:
        """Ids of the landmarks observed in a frame."""
        return set(self._obs_in_frame.get(frame_id, ()))

    def remove_frame(self, frame_id: int) -> list[int]:
        """Drop all observations made in a frame and all landmarks it hosts; returns the ids
        of the removed landmarks."""
        ids = self._obs_in_frame.pop(frame_id, None)
        if ids:
            self._flush()
            slots = [self._obs[lm_id].pop(frame_id) for lm_id in ids]
            self._o_alive[slots] = False
            self._n_alive -= len(slots)
            self._version += 1
        removed = sorted(self._hosted.get(frame_id, ()))
        for lm_id in removed:
            self.remove_landmark(lm_id)
        self._hosted.pop(frame_id, None)
        return removed

    @property
    def num_observations(self) -> int:
        return self._n_alive

    # ------------------------------------------------------------ slot storage
    def _observation_at(self, slot: int) -> Observation:
        if slot >= self._n_flushed:
            i = slot - self._n_flushed
            return Observation(np.array([self._p_u[i], self._p_v[i]]), self._p_level[i])
        return Observation(self._o_uv[slot].copy(), int(self._o_level[slot]))

    def _kill(self, slot: int) -> None:
        if slot >= self._n_flushed:
            self._flush()
        self._o_alive[slot] = False
        self._n_alive -= 1

    def _reserve(self, size: int) -> None:
        cap = self._o_lm.shape[0]
        if size <= cap:
            return
        cap = max(2 * cap, size)
        n = self._n_flushed
        for name in ("_o_lm", "_o_frame", "_o_uv", "_o_level", "_o_alive"):
            old = getattr(self, name)
            new = np.zeros((cap,) + old.shape[1:], dtype=old.dtype)
            new[:n] = old[:n]
            setattr(self, name, new)

    def _flush(self) -> None:
        """Move pending observations into the slot arrays."""
        k = len(self._p_lm)
        if k == 0:
            return
        n = self._n_flushed
        self._reserve(n + k)
        self._o_lm[n:n + k] = self._p_lm
        self._o_frame[n:n + k] = self._p_frame
        self._o_uv[n:n + k, 0] = self._p_u
        self._o_uv[n:n + k, 1] = self._p_v
        self._o_level[n:n + k] = self._p_level
        self._o_alive[n:n + k] = True
        self._n_flushed = n + k
        self._p_lm, self._p_frame, self._p_u, self._p_v, self._p_level = [], [], [], [], []

    def _compact(self) -> None:
        """Drop dead slots (keeps the order of the live ones) and renumber the index."""
        n = self._n_flushed
        keep = np.flatnonzero(self._o_alive[:n])
        m = keep.shape[0]
        remap = np.full(n, -1, dtype=np.int64)
        remap[keep] = np.arange(m, dtype=np.int64)
        new_slot = remap.tolist()
        for d in self._obs.values():
            for f, s in d.items():
                d[f] = new_slot[s]
        for name in ("_o_lm", "_o_frame", "_o_uv", "_o_level"):
            arr = getattr(self, name)
            arr[:m] = arr[keep]
        self._o_alive[:m] = True
        self._o_alive[m:n] = False
        self._n_flushed = m

    # ------------------------------------------------------------------- packing
    def pack(self, frame_index: dict[int, int], landmark_ids: Iterable[int] | None = None,
             target_filter: set[int] | None = None) -> PackedObservations:
        """Flatten landmarks and observations into arrays for the kernels.

        Args:
            frame_index: frame id -> pose index; observations in frames not in it are skipped.
            landmark_ids: landmarks to include (default: all, in id order).
            target_filter: if given, only observations made in these frames are included.

        Observations are grouped by landmark (in the order of ``landmark_ids``) and, within a
        landmark, in the order they were added. The observation structure is cached until the
        next change of landmarks or observations; landmark states are read on every call.
        """
        self._flush()
        dead = self._n_flushed - self._n_alive
        if dead > self._MIN_COMPACT and dead > self._n_alive:
            self._compact()
        ids = None if landmark_ids is None else list(landmark_ids)
        key = (self._version, tuple(frame_index.items()), None if ids is None else tuple(ids),
               None if target_filter is None else frozenset(target_filter))
        cache = self._pack_cache
        if cache is not None and cache[0] == key:
            struct = cache[1]
        else:
            struct = self._pack_structure(frame_index, ids, target_filter)
            self._pack_cache = (key, struct)
        ids_arr, lms, lm_host, lm_ptr, obs_lm, obs_tgt, obs_uv, obs_level = struct
        m = len(lms)
        return PackedObservations(
            landmark_ids=ids_arr.copy(),
            lm_host=lm_host.copy(),
            lm_s=self._gather_s(lms),
            lm_d=np.fromiter([lm.inv_dist for lm in lms], dtype=np.float64, count=m),
            lm_ptr=lm_ptr.copy(),
            obs_lm=obs_lm.copy(),
            obs_tgt=obs_tgt.copy(),
            obs_uv=obs_uv.copy(),
            obs_level=obs_level.copy(),
        )

    def _pack_structure(self, frame_index: dict[int, int], ids: list[int] | None,
                        target_filter: set[int] | None) -> tuple:
        if ids is None:
            ids = sorted(self._landmarks)
        lms = [self._landmarks[i] for i in ids]
        m = len(ids)
        ids_arr = np.array(ids, dtype=np.int64).reshape(m)
        lm_host = np.array([frame_index[lm.host_frame_id] for lm in lms],
                           dtype=np.int64).reshape(m)
        slots = np.flatnonzero(self._o_alive[:self._n_flushed])
        # landmark row of every live slot (or none)
        o_lm = self._o_lm[slots]
        sorter = np.argsort(ids_arr, kind="stable")
        sorted_ids = ids_arr[sorter]
        pos = np.minimum(np.searchsorted(sorted_ids, o_lm), max(m - 1, 0))
        ok = sorted_ids[pos] == o_lm if m else np.zeros(slots.shape[0], dtype=bool)
        row = sorter[pos] if m else pos
        # pose index of the observing frame (or none)
        nf = len(frame_index)
        f_ids = np.fromiter(frame_index.keys(), dtype=np.int64, count=nf)
        f_pos = np.fromiter(frame_index.values(), dtype=np.int64, count=nf)
        f_sort = np.argsort(f_ids, kind="stable")
        f_ids, f_pos = f_ids[f_sort], f_pos[f_sort]
        o_frame = self._o_frame[slots]
        fp = np.minimum(np.searchsorted(f_ids, o_frame), max(nf - 1, 0))
        ok &= (f_ids[fp] == o_frame) if nf else False
        if target_filter is not None:
            flt = np.fromiter((int(f) for f in target_filter), dtype=np.int64)
            ok &= np.isin(o_frame, flt)
        sel = np.flatnonzero(ok)
        order = sel[np.argsort(row[sel], kind="stable")]
        obs_lm = row[order]
        obs_slots = slots[order]
        lm_ptr = np.zeros(m + 1, dtype=np.int64)
        np.cumsum(np.bincount(obs_lm, minlength=m), out=lm_ptr[1:])
        return (ids_arr, lms, lm_host, lm_ptr, obs_lm, f_pos[fp[order]],
                self._o_uv[obs_slots], self._o_level[obs_slots])

    def _gather_s(self, lms: list[Landmark]) -> np.ndarray:
        """Stereographic bearings (M, 2) of landmarks. Fast path: the bearings are still the
        row views written by the last :meth:`unpack_states` (in the same order)."""
        ss = [lm.s for lm in lms]
        store = self._s_store
        if (store is not None and len(store[0]) == len(ss) > 0
                and all(map(operator.is_, ss, store[0])) and ss[0].base is store[1]):
            return store[1].copy()
        return np.array(ss, dtype=np.float64).reshape(len(ss), 2)

    def unpack_states(self, packed: PackedObservations) -> None:
        """Write the landmark states (``lm_s``, ``lm_d``) of a packed problem back. Each
        landmark's ``s`` becomes a row view of one private copy of ``packed.lm_s``."""
        store = np.array(packed.lm_s, dtype=np.float64, order="C", copy=True)
        views = list(store)
        lms = self._landmarks
        for lm_id, s, d in zip(packed.landmark_ids.tolist(), views, packed.lm_d.tolist()):
            lm = lms[lm_id]
            lm.s = s
            lm.inv_dist = d
        self._s_store = (views, store)
