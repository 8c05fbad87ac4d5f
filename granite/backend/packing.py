"""Packing the landmark database into flat arrays for the numba kernels.

:class:`PackedObservations` is what the linearisation kernels (:mod:`granite.backend.reprojection`)
and the Schur complement (:mod:`granite.backend.schur`) read: landmark rows, observations grouped
by landmark, pose indices instead of frame ids.
"""

from __future__ import annotations

import dataclasses

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
    ``KeyError`` when a host is not in ``frame_index``."""
    m = ids_arr.shape[0]
    # pose index of the observing frame (or none)
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
    live = slots.live_slots()
    # landmark row of every live slot (or none)
    o_lm = slots.landmark_ids(live)
    sorter = np.argsort(ids_arr, kind="stable")
    sorted_ids = ids_arr[sorter]
    pos = np.minimum(np.searchsorted(sorted_ids, o_lm), max(m - 1, 0))
    ok = sorted_ids[pos] == o_lm if m else np.zeros(live.shape[0], dtype=bool)
    row = sorter[pos] if m else pos
    o_frame = slots.frame_ids(live)
    fp = np.minimum(np.searchsorted(f_ids, o_frame), max(nf - 1, 0))
    ok &= (f_ids[fp] == o_frame) if nf else False
    if target_filter is not None:
        flt = np.fromiter((int(f) for f in target_filter), dtype=np.int64)
        ok &= np.isin(o_frame, flt)
    sel = np.flatnonzero(ok)
    order = sel[np.argsort(row[sel], kind="stable")]
    obs_lm = row[order]
    obs_slots = live[order]
    lm_ptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(np.bincount(obs_lm, minlength=m), out=lm_ptr[1:])
    return (lm_host, lm_ptr, obs_lm, f_pos[fp[order]], slots.pixels(obs_slots),
            slots.levels(obs_slots))
