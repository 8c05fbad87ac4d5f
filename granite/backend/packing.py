"""Packing the landmark database into flat arrays for the numba kernels.

:class:`PackedObservations` is what the linearisation kernels (:mod:`granite.backend.reprojection`)
and the Schur complement (:mod:`granite.backend.schur`) read: landmark rows, observations grouped
by landmark, pose indices instead of frame ids.
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from granite.backend.observation_store import ObservationSlots


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


def pack_structure(ids_arr: np.ndarray, host_frames: np.ndarray, slots: ObservationSlots,
                   frame_index: dict[int, int], target_filter: set[int] | None) -> tuple:
    """The observation structure of a packed problem (everything but the landmark states) of
    the landmarks ``ids_arr`` (M,) hosted by the frames ``host_frames`` (M,):
    ``(lm_host, lm_ptr, obs_lm, obs_tgt, obs_uv, obs_level)``. ``slots`` must be flushed;
    ``KeyError`` when a host is not in ``frame_index``. The observations of a landmark are
    in slot order; a landmark listed twice gets them at its first place."""
    m = ids_arr.shape[0]
    nf = len(frame_index)
    f_ids = np.fromiter(frame_index.keys(), dtype=np.int64, count=nf)
    f_pos = np.fromiter(frame_index.values(), dtype=np.int64, count=nf)
    f_sort = np.argsort(f_ids, kind="stable")
    f_ids, f_pos = f_ids[f_sort], f_pos[f_sort]
    hp = np.minimum(np.searchsorted(f_ids, host_frames), max(nf - 1, 0))
    host_ok = (f_ids[hp] == host_frames) if nf else np.zeros(m, dtype=bool)
    if not np.all(host_ok):
        raise KeyError(int(host_frames[np.flatnonzero(~host_ok)[0]]))
    lm_host = f_pos[hp] if m else np.zeros(0, dtype=np.int64)
    flt = np.zeros(0, dtype=np.int64) if target_filter is None else \
        np.fromiter((int(f) for f in target_filter), dtype=np.int64)
    alive, o_lm, o_frame, o_uv, o_level = slots.arrays()
    lm_ptr, obs_lm, obs_tgt, obs_uv, obs_level = _pack_observations(
        alive, o_lm, o_frame, o_uv, o_level, ids_arr, f_ids, f_pos, target_filter is not None,
        flt)
    return lm_host, lm_ptr, obs_lm, obs_tgt, obs_uv, obs_level


@numba.njit(cache=True, nogil=True)
def _id_lookup(key, dense, lo, table, sorted_keys, sorted_values):
    """The value of integer ``key`` (-1: not listed): from ``table`` over the key range
    starting at ``lo`` when ``dense``, else by a sorted search in ``sorted_keys``."""
    if dense:
        x = key - lo
        if x < 0 or x >= table.shape[0]:
            return -1
        return table[x]
    p = np.searchsorted(sorted_keys, key)
    if p >= sorted_keys.shape[0] or sorted_keys[p] != key:
        return -1
    return sorted_values[p]


@numba.njit(cache=True, nogil=True)
def _pack_observations(alive, o_lm, o_frame, o_uv, o_level, ids, f_ids, f_pos, use_filter, flt):
    """The live slots observing a listed landmark (``ids``; the first place of an id listed
    twice) in a listed frame (``f_ids``, pose ``f_pos``; and in ``flt`` with ``use_filter``),
    grouped by landmark place in slot order (a counting sort): ``(lm_ptr, obs_lm, obs_tgt,
    obs_uv, obs_level)``. Ids are looked up in tables over their range (a sorted search when
    the landmark ids are too spread out for one)."""
    n = alive.shape[0]
    m = ids.shape[0]
    nf = f_ids.shape[0]
    counts = np.zeros(m + 1, dtype=np.int64)
    row = np.full(n, -1, dtype=np.int64)
    tgt = np.empty(n, dtype=np.int64)
    if m > 0 and nf > 0:
        # frames: pose index (or -1: not listed or filtered out), in a table over the range
        # of the listed frame ids, or found by a sorted search when they are spread out
        f_lo = f_ids.min()
        f_span = f_ids.max() - f_lo + 1
        f_dense = f_span <= 4 * (nf + n) + 4096
        f_sorted = np.sort(f_ids)
        f_at = f_pos[np.argsort(f_ids, kind="mergesort")]
        if use_filter:
            flt_sorted = np.sort(flt)
            for q in range(nf):
                p = np.searchsorted(flt_sorted, f_sorted[q])
                if p >= flt_sorted.shape[0] or flt_sorted[p] != f_sorted[q]:
                    f_at[q] = -1
        f_table = np.full(f_span if f_dense else 0, -1, dtype=np.int64)
        if f_dense:
            for q in range(nf):
                f_table[f_sorted[q] - f_lo] = f_at[q]
        lo = ids.min()
        span = ids.max() - lo + 1
        dense = span <= 4 * (m + n) + 4096
        table = np.full(span if dense else 0, -1, dtype=np.int64)
        if dense:  # backwards: an id listed twice keeps its first place
            for i in range(m - 1, -1, -1):
                table[ids[i] - lo] = i
        # stable: an id listed twice is found at its first place (unused when dense)
        sorter = np.argsort(ids if not dense else ids[:0], kind="mergesort")
        sorted_ids = ids[sorter]
        for k in range(n):
            if not alive[k]:
                continue
            t = _id_lookup(o_frame[k], f_dense, f_lo, f_table, f_sorted, f_at)
            if t < 0:
                continue
            i = _id_lookup(o_lm[k], dense, lo, table, sorted_ids, sorter)
            if i < 0:
                continue
            row[k] = i
            tgt[k] = t
            counts[i + 1] += 1
    lm_ptr = np.cumsum(counts)
    total = lm_ptr[m]
    obs_lm = np.empty(total, dtype=np.int64)
    obs_tgt = np.empty(total, dtype=np.int64)
    obs_uv = np.empty((total, 2))
    obs_level = np.empty(total, dtype=np.int64)
    fill = lm_ptr[:m].copy()
    for k in range(n):
        i = row[k]
        if i < 0:
            continue
        j = fill[i]
        fill[i] = j + 1
        obs_lm[j] = i
        obs_tgt[j] = tgt[k]
        obs_uv[j, 0] = o_uv[k, 0]
        obs_uv[j, 1] = o_uv[k, 1]
        obs_level[j] = o_level[k]
    return lm_ptr, obs_lm, obs_tgt, obs_uv, obs_level
