"""Landmarks (bearing + inverse distance in a host keyframe) and their observations.

A landmark ``l`` is hosted by a keyframe ``h``: its homogeneous position in the host camera
frame is ``[b, d]`` with ``b`` a unit bearing (3,) and ``d >= 0`` the inverse distance
[1 / map unit]; the Euclidean point is ``b / d`` and ``d = 0`` is a point at infinity (paper
Sec. IV-B). In any target frame ``t`` the point is, up to a positive scale,
``p_t = R_t_h b + t_t_h d`` (valid at ``d = 0``). The bearing is stored as its stereographic
parameter ``s`` (2,), see :mod:`granite.backend.stereographic`.

Observations ``z`` are pixel coordinates (u, v) with the pyramid level ``c`` the feature was
created on (weight ``2**-c``, paper Eq. 7).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from granite.backend.observation_store import Observation, ObservationSlots
from granite.backend.packing import PackedObservations, pack_structure
from granite.backend.stereographic import bearings_from_stereo, stereo_from_bearing3


class _StateStore:
    """Landmark states in growable arrays, one row per landmark: stereographic bearing ``s``
    (2,), inverse distance ``d`` and host frame id; rows ``[0, n)`` are in use."""

    __slots__ = ("s", "d", "host", "n")

    def __init__(self, capacity: int = 256) -> None:
        self.s = np.empty((capacity, 2))
        self.d = np.empty(capacity)
        self.host = np.empty(capacity, dtype=np.int64)
        self.n = 0

    def append(self, host: int, s: np.ndarray, d: float) -> int:
        row = self.n
        if row == self.d.shape[0]:
            cap = 2 * row
            for name in ("s", "d", "host"):
                old = getattr(self, name)
                new = np.empty((cap,) + old.shape[1:], dtype=old.dtype)
                new[:row] = old
                setattr(self, name, new)
        self.s[row] = s
        self.d[row] = d
        self.host[row] = host
        self.n = row + 1
        return row


class Landmark:
    """State of one landmark: host keyframe id, stereographic bearing ``s`` (2,) in the host
    camera frame and inverse distance ``inv_dist`` (``>= 0``, 0 = at infinity).

    A landmark of a :class:`LandmarkDatabase` is a view of one row of the database's state
    arrays (``s`` is a (2,) view of it: editing it in place edits the database; assigning
    ``s`` or ``inv_dist`` writes the row); one removed from its database keeps its last
    state. ``Landmark(host, s, inv_dist)`` makes a standalone one."""

    __slots__ = ("host_frame_id", "_store", "_row")

    def __init__(self, host_frame_id: int, s: np.ndarray, inv_dist: float) -> None:
        self.host_frame_id = int(host_frame_id)
        self._store = _StateStore(1)
        self._row = self._store.append(self.host_frame_id, s, inv_dist)

    @classmethod
    def _of(cls, store: _StateStore, row: int) -> Landmark:
        lm = object.__new__(cls)
        lm.host_frame_id = int(store.host[row])
        lm._store = store
        lm._row = row
        return lm

    def _detach(self) -> None:
        """Keep the current state in a private store (the landmark left its database)."""
        st = self._store
        self._store = _StateStore(1)
        self._row = self._store.append(self.host_frame_id, st.s[self._row], st.d[self._row])

    @property
    def s(self) -> np.ndarray:
        return self._store.s[self._row]

    @s.setter
    def s(self, value) -> None:
        self._store.s[self._row] = value

    @property
    def inv_dist(self) -> float:
        return float(self._store.d[self._row])

    @inv_dist.setter
    def inv_dist(self, value: float) -> None:
        self._store.d[self._row] = value

    def __repr__(self) -> str:
        return f"Landmark(host_frame_id={self.host_frame_id}, s={self.s!r}, inv_dist={self.inv_dist!r})"

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


#: Landmark ids below this (and not negative) are looked up in a table indexed by id (the
#: frontend's track ids are small consecutive integers); any other id switches the database to
#: dictionary lookups.
_MAX_TABLE_ID = 1 << 24


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

    Observations live in :class:`~granite.backend.observation_store.ObservationSlots`;
    ``frame -> {landmark -> slot}`` indexes them (a frame's observations are added and
    dropped together, one dictionary each; a landmark's are found through the window's few
    frames). Within a landmark, slot order is the order in which its observations were added
    (a replaced observation keeps its place), which is the order :meth:`pack` uses. Dead
    slots are compacted away when they outnumber the live ones and exceed
    ``compact_threshold`` (memory only: packing gives the same arrays either way). The landmark states (bearing, inverse distance, host) are rows
    of arrays (:class:`Landmark` objects are views of them), so packing, unpacking and the
    per-id queries are vectorised gathers; ids that are small non-negative integers (track
    ids) are found through a table indexed by id, other ids through the dictionary.
    """

    def __init__(self, compact_threshold: int = 4096) -> None:
        self.compact_threshold = int(compact_threshold)
        self._landmarks: dict[int, Landmark] = {}
        self._obs_in_frame: dict[int, dict[int, int]] = {}  # frame -> {landmark -> slot}
        self._hosted: dict[int, set[int]] = {}
        self._slots = ObservationSlots()
        self._version = 0  # bumped on every change of landmarks / observations (not states)
        self._state_version = 0  # bumped by every state write of the database's own methods
        self._pack_cache: tuple | None = None
        # landmark states: one row per landmark (rows of removed ones are dead until the
        # store is compacted), and the row of each id (-1: none) while ids fit a table
        self._store = _StateStore()
        self._row_of: np.ndarray | None = np.full(1024, -1, dtype=np.int64)

    def __getstate__(self) -> dict:
        """Pickle / deepcopy without the cache of the packed structure."""
        state = self.__dict__.copy()
        state["_pack_cache"] = None
        return state

    def _rows(self, ids: np.ndarray) -> np.ndarray:
        """State rows (n,) of landmark ids (n,) int64; -1 for ids that are not landmarks."""
        table = self._row_of
        if table is None:
            lms = self._landmarks
            return np.array([lms[i]._row if i in lms else -1 for i in ids.tolist()],
                            dtype=np.int64).reshape(-1)
        inside = (ids >= 0) & (ids < table.shape[0])
        if inside.all():
            return table[ids]
        return np.where(inside, table[np.where(inside, ids, 0)], -1)

    def _compact_states(self) -> None:
        """Drop the rows of removed landmarks (order kept); renumbers the landmark views."""
        st = self._store
        lms = list(self._landmarks.values())
        rows = np.array([lm._row for lm in lms], dtype=np.int64)
        order = np.argsort(rows, kind="stable")
        new = _StateStore(max(256, 2 * len(lms)))
        n = len(lms)
        keep = rows[order]
        new.s[:n] = st.s[keep]
        new.d[:n] = st.d[keep]
        new.host[:n] = st.host[keep]
        new.n = n
        for r, k in enumerate(order.tolist()):
            lm = lms[k]
            lm._store = new
            lm._row = r
        self._store = new
        if self._row_of is not None:
            self._row_of[:] = -1
            ids = np.fromiter(self._landmarks.keys(), dtype=np.int64, count=n)
            self._row_of[ids[order]] = np.arange(n, dtype=np.int64)
        self._pack_cache = None

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
        s = stereo_from_bearing3(np.asarray(bearing, dtype=np.float64).reshape(3))
        st = self._store
        if st.n - len(self._landmarks) > max(1024, len(self._landmarks)):
            self._compact_states()
            st = self._store
        row = st.append(int(host_frame_id), s, float(inv_dist))
        self._landmarks[landmark_id] = Landmark._of(st, row)
        table = self._row_of
        if table is not None:
            lid = int(landmark_id)
            if 0 <= lid < _MAX_TABLE_ID and lid == landmark_id:
                if lid >= table.shape[0]:
                    grown = np.full(max(2 * table.shape[0], lid + 1), -1, dtype=np.int64)
                    grown[:table.shape[0]] = table
                    self._row_of = table = grown
                table[lid] = row
            else:
                self._row_of = None
        self._hosted.setdefault(int(host_frame_id), set()).add(landmark_id)
        self._version += 1

    def set_inverse_distance(self, landmark_id: int, inv_dist: float) -> None:
        """Overwrite a landmark's inverse distance (``>= 0``; 0 = at infinity)."""
        if not (math.isfinite(inv_dist) and inv_dist >= 0.0):
            raise ValueError(f"landmark {landmark_id}: inverse distance must be >= 0, "
                             f"got {inv_dist}")
        self._landmarks[landmark_id].inv_dist = inv_dist
        self._state_version += 1

    def remove_landmark(self, landmark_id: int) -> None:
        lm = self._landmarks.pop(landmark_id)
        for in_frame in self._obs_in_frame.values():
            slot = in_frame.pop(landmark_id, None)
            if slot is not None:
                self._slots.kill(slot)
        self._hosted[lm.host_frame_id].discard(landmark_id)
        if self._row_of is not None:
            self._row_of[landmark_id] = -1
        lm._detach()
        self._version += 1

    def ids_by_host(self, hosts) -> np.ndarray:
        """Ids (n,) of the landmarks hosted by the frames ``hosts`` (ascending ids), host by
        host in ascending host id, ascending within a host."""
        n = len(self._landmarks)
        ids = np.fromiter(self._landmarks.keys(), dtype=np.int64, count=n)
        host = self._store.host[self._rows(ids)]
        keep = np.isin(host, np.asarray(list(hosts), dtype=np.int64))
        ids, host = ids[keep], host[keep]
        return ids[np.lexsort((ids, host))]

    def hosted_by(self, frame_id: int) -> set[int]:
        """Ids of the landmarks hosted by a frame."""
        return set(self._hosted.get(frame_id, ()))

    def num_connected(self, frame_id: int) -> tuple[int, int]:
        """``(finite, infinite)``: landmarks observed in a frame with ``d > 0`` and otherwise."""
        ids = self._obs_in_frame.get(frame_id)
        if not ids:
            return 0, 0
        rows = self._rows(np.fromiter(ids, dtype=np.int64, count=len(ids)))
        finite = int(np.count_nonzero(self._store.d[rows] > 0.0))
        return finite, len(ids) - finite

    def inverse_distances(self, landmark_ids) -> np.ndarray:
        """Inverse distances (n,) of the given ids, NaN for ids that are not landmarks."""
        rows = self._rows(np.asarray(landmark_ids, dtype=np.int64).reshape(-1))
        out = np.full(rows.shape[0], math.nan)
        known = rows >= 0
        out[known] = self._store.d[rows[known]]
        return out

    def states_of(self, landmark_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(s (n, 2), inv_dist (n,), host frame ids (n,))`` of the given ids (copies;
        ``KeyError`` for an id that is not a landmark)."""
        ids = np.asarray(landmark_ids, dtype=np.int64).reshape(-1)
        rows = self._rows(ids)
        if np.any(rows < 0):
            raise KeyError(int(ids[np.flatnonzero(rows < 0)[0]]))
        st = self._store
        return st.s[rows], st.d[rows], st.host[rows]

    def landmarks_of(self, landmark_ids) -> list[Landmark]:
        """The landmarks of the given ids (``KeyError`` for an unknown one), in order."""
        lms = self._landmarks
        return [lms[i] for i in np.asarray(landmark_ids, dtype=np.int64).reshape(-1).tolist()]

    # -------------------------------------------------------------- observations
    def add_observation(self, landmark_id: int, frame_id: int, uv: np.ndarray,
                        level: int = 0) -> None:
        """Add (or replace) the observation of a landmark in a frame."""
        if landmark_id not in self._landmarks:
            raise KeyError(f"observation of unknown landmark {landmark_id}")
        u, v = _uv_pair(uv)
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ValueError(f"observation of landmark {landmark_id} in frame {frame_id} "
                             "is not finite")
        frame_id = int(frame_id)
        level = int(level)
        in_frame = self._obs_in_frame.get(frame_id)
        if in_frame is None:
            in_frame = self._obs_in_frame[frame_id] = {}
        slot = in_frame.get(landmark_id)
        if slot is None:
            in_frame[landmark_id] = self._slots.append(landmark_id, frame_id, u, v, level)
        else:
            self._slots.set(slot, u, v, level)
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
        lms = self._landmarks
        ids_list = ids.tolist()
        if self._row_of is not None:
            known = np.flatnonzero(self._rows(ids) >= 0).tolist()
        else:
            known = [k for k, i in enumerate(ids_list) if i in lms]
        if len(known) != n:
            if not skip_unknown:
                raise KeyError("observation of unknown landmark "
                               f"{next(i for i in ids_list if i not in lms)}")
            ids_list = [ids_list[k] for k in known]
            ids, uvs, lv = ids[known], uvs[known], lv[known]
            n = len(known)
        if n == 0:
            return 0
        if not np.all(np.isfinite(uvs)):
            raise ValueError(f"observations in frame {fid} are not finite")
        self._slots.flush()
        base = self._slots.next_slot
        in_frame = self._obs_in_frame.get(fid)
        if not in_frame:
            # the usual case, a new frame: no landmark has an observation in it yet; when no
            # id repeats either, every observation gets the next slot
            fresh = dict(zip(ids_list, range(base, base + n)))
            if len(fresh) == n:
                self._obs_in_frame[fid] = fresh
                self._slots.extend(ids, fid, uvs, lv)
                self._version += 1
                return n
        if in_frame is None:
            in_frame = self._obs_in_frame[fid] = {}
        nxt = base
        new_rows: list[int] = []
        replaced: list[tuple[int, int]] = []
        for k, lm_id in enumerate(ids_list):
            slot = in_frame.get(lm_id)
            if slot is None:
                in_frame[lm_id] = nxt
                nxt += 1
                new_rows.append(k)
            else:
                replaced.append((slot, k))
        if nxt > base:
            sel = slice(None) if nxt - base == n else np.asarray(new_rows, dtype=np.int64)
            self._slots.extend(ids[sel], fid, uvs[sel], lv[sel])
        for slot, k in replaced:
            self._slots.set_flushed(slot, uvs[k], lv[k])
        self._version += 1
        return n

    def remove_observation(self, landmark_id: int, frame_id: int) -> None:
        slot = self._obs_in_frame[frame_id].pop(landmark_id)
        self._slots.kill(slot)
        self._version += 1

    def observations(self, landmark_id: int) -> dict[int, Observation]:
        """Observations of a landmark: frame id -> observation, in the order they were added."""
        if landmark_id not in self._landmarks:
            raise KeyError(landmark_id)
        slots = sorted((d[landmark_id], f) for f, d in self._obs_in_frame.items() if landmark_id in d)
        return {f: self._slots.get(s) for s, f in slots}

    def observation(self, landmark_id: int, frame_id: int) -> Observation:
        """The observation of a landmark in a frame (``KeyError`` if there is none)."""
        return self._slots.get(self._obs_in_frame[frame_id][landmark_id])

    def has_observation(self, landmark_id: int, frame_id: int) -> bool:
        in_frame = self._obs_in_frame.get(frame_id)
        return in_frame is not None and landmark_id in in_frame

    def observed_in(self, frame_id: int) -> set[int]:
        """Ids of the landmarks observed in a frame."""
        return set(self._obs_in_frame.get(frame_id, ()))

    def num_scale_links(self, frame_id: int, keyframes: Iterable[int]) -> int:
        """Finite landmarks (``d > 0``) observed in ``frame_id`` and in at least two of
        ``keyframes`` other than it (the host's own observation counts): those that carry the
        map's scale to the frame. A landmark seen in two frames only fixes their relative pose
        up to the length of the baseline."""
        kfs = set(keyframes) - {frame_id}
        in_kfs = [d for f, d in self._obs_in_frame.items() if f in kfs]
        ids = [lm for lm in self._obs_in_frame.get(frame_id, ())
               if sum(1 for d in in_kfs if lm in d) >= 2]
        if not ids:
            return 0
        return int(np.count_nonzero(self.inverse_distances(np.asarray(ids, dtype=np.int64)) > 0.0))

    def remove_frame(self, frame_id: int) -> list[int]:
        """Drop all observations made in a frame and all landmarks it hosts; returns the ids
        of the removed landmarks."""
        in_frame = self._obs_in_frame.pop(frame_id, None)
        if in_frame:
            self._slots.kill_many(list(in_frame.values()))
            self._version += 1
        removed = sorted(self._hosted.get(frame_id, ()))
        for lm_id in removed:
            self.remove_landmark(lm_id)
        self._hosted.pop(frame_id, None)
        return removed

    @property
    def version(self) -> tuple[int, int]:
        """Changes whenever a landmark, an observation or a state changes through the
        database's methods (not through in-place edits of a :class:`Landmark`'s ``s`` view)."""
        return self._version, self._state_version

    @property
    def num_observations(self) -> int:
        return self._slots.num_alive

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
        self._slots.flush()
        dead = self._slots.num_dead
        if dead > self.compact_threshold and dead > self._slots.num_alive:
            new_slot = self._slots.compact()
            for d in self._obs_in_frame.values():
                for lm_id, s in d.items():
                    d[lm_id] = new_slot[s]
        ids = None if landmark_ids is None else list(landmark_ids)
        key = (self._version, tuple(frame_index.items()), None if ids is None else tuple(ids),
               None if target_filter is None else frozenset(target_filter))
        cache = self._pack_cache
        if cache is not None and cache[0] == key:
            struct = cache[1]
        else:
            ids_arr = np.array(sorted(self._landmarks) if ids is None else ids,
                               dtype=np.int64).reshape(-1)
            rows = self._rows(ids_arr)
            if np.any(rows < 0):
                raise KeyError(int(ids_arr[np.flatnonzero(rows < 0)[0]]))
            struct = (ids_arr, rows) + pack_structure(ids_arr, self._store.host[rows],
                                                      self._slots, frame_index, target_filter)
            self._pack_cache = (key, struct)
        ids_arr, rows, lm_host, lm_ptr, obs_lm, obs_tgt, obs_uv, obs_level = struct
        st = self._store
        return PackedObservations(
            landmark_ids=ids_arr.copy(),
            lm_host=lm_host.copy(),
            lm_s=st.s[rows],
            lm_d=st.d[rows],
            lm_ptr=lm_ptr.copy(),
            obs_lm=obs_lm.copy(),
            obs_tgt=obs_tgt.copy(),
            obs_uv=obs_uv.copy(),
            obs_level=obs_level.copy(),
        )

    def unpack_states(self, packed: PackedObservations) -> None:
        """Write the landmark states (``lm_s``, ``lm_d``) of a packed problem back."""
        ids = np.asarray(packed.landmark_ids, dtype=np.int64).reshape(-1)
        rows = self._rows(ids)
        if np.any(rows < 0):
            raise KeyError(int(ids[np.flatnonzero(rows < 0)[0]]))
        st = self._store
        st.s[rows] = packed.lm_s
        st.d[rows] = packed.lm_d
        self._state_version += 1
