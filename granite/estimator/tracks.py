"""The frontend's tracks of the frames in the window, as the estimator keeps them."""

from __future__ import annotations

import numba
import numpy as np

from granite.optical_flow import OpticalFlowResult


class FrameTracks:
    """Tracks of one frame by track id: pixel position ``(u, v)`` and the pyramid level the
    feature was created on. Track ids are the landmark ids of the backend. ``ids`` (n,),
    ``uv`` (n, 2) and ``level_values`` (n,) hold the tracks as arrays, in the frontend's
    order; ``positions`` and ``levels`` are the same as dictionaries by id, made on first use
    (most frames are never looked up by id). ``FrameTracks(positions, levels)`` builds the
    arrays from the dictionaries."""

    __slots__ = ("ids", "uv", "level_values", "_positions", "_levels", "_bearings")

    def __init__(self, positions: dict[int, np.ndarray] | None, levels: dict[int, int] | None,
                 ids: np.ndarray | None = None, uv: np.ndarray | None = None,
                 level_values: np.ndarray | None = None) -> None:
        self._positions = positions
        self._levels = levels
        self._bearings: tuple[np.ndarray, np.ndarray] | None = None
        if ids is None:  # built from the dictionaries alone
            assert positions is not None and levels is not None
            self.ids = np.fromiter(positions, dtype=np.int64, count=len(positions))
            self.uv = np.array(list(positions.values()), dtype=np.float64).reshape(-1, 2)
            self.level_values = np.fromiter((levels[i] for i in positions), dtype=np.int64,
                                            count=len(positions))
        else:
            self.ids, self.uv, self.level_values = ids, uv, level_values

    @property
    def positions(self) -> dict[int, np.ndarray]:
        if self._positions is None:
            self._positions = dict(zip(self.ids.tolist(), self.uv))
        return self._positions

    @property
    def levels(self) -> dict[int, int]:
        if self._levels is None:
            self._levels = dict(zip(self.ids.tolist(), self.level_values.tolist()))
        return self._levels

    @classmethod
    def from_result(cls, result: OpticalFlowResult) -> FrameTracks:
        return cls(None, None, result.ids.copy(), result.positions.copy(), result.levels.copy())

    def bearings(self, unproject) -> tuple[np.ndarray, np.ndarray]:
        """Unit bearings (n, 3) and validity (n,) of ``uv`` by ``unproject`` (pixels (n, 2) ->
        both; e.g. ``LandmarkTriangulator.bearings``), computed on the first call and kept:
        one camera per estimator."""
        if self._bearings is None:
            self._bearings = unproject(self.uv)
        return self._bearings


def shared_tracks(cur: FrameTracks, ref: FrameTracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracks of ``cur`` that ``ref`` has too, in ``cur``'s order: ``(ids, rows in cur,
    rows in ref)`` (track ids are unique within a frame)."""
    rows_cur, rows_ref = _shared_rows(cur.ids, ref.ids)
    return cur.ids[rows_cur], rows_cur, rows_ref


@numba.njit(cache=True, nogil=True)
def _shared_rows(cur_ids: np.ndarray, ref_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the ids both arrays hold, in ``cur_ids``' order (ids unique in each): binary
    search in the sorted ``ref_ids``."""
    order = np.argsort(ref_ids)
    sorted_ref = ref_ids[order]
    pos = np.searchsorted(sorted_ref, cur_ids)
    m = len(sorted_ref)
    rows_cur = np.empty(len(cur_ids), dtype=np.int64)
    rows_ref = np.empty(len(cur_ids), dtype=np.int64)
    k = 0
    for i in range(len(cur_ids)):
        p = pos[i]
        if p < m and sorted_ref[p] == cur_ids[i]:
            rows_cur[k] = i
            rows_ref[k] = order[p]
            k += 1
    return rows_cur[:k], rows_ref[:k]
