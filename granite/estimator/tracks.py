"""The frontend's tracks of the frames in the window, as the estimator keeps them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from granite.optical_flow import OpticalFlowResult


@dataclass
class FrameTracks:
    """Tracks of one frame by track id: pixel position ``(u, v)`` and the pyramid level the
    feature was created on. Track ids are the landmark ids of the backend. ``ids`` (n,) and
    ``uv`` (n, 2) hold the same tracks as arrays, in the frontend's order (made from the
    dictionaries when not given)."""

    positions: dict[int, np.ndarray]
    levels: dict[int, int]
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    _bearings: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.ids) != len(self.positions):  # built from the dictionaries alone
            self.ids = np.fromiter(self.positions, dtype=np.int64, count=len(self.positions))
            self.uv = np.array(list(self.positions.values()), dtype=np.float64).reshape(-1, 2)

    @classmethod
    def from_result(cls, result: OpticalFlowResult) -> FrameTracks:
        ids = result.ids.tolist()
        return cls(dict(zip(ids, result.positions)), dict(zip(ids, result.levels.tolist())),
                   result.ids.copy(), result.positions.copy())

    def bearings(self, unproject) -> tuple[np.ndarray, np.ndarray]:
        """Unit bearings (n, 3) and validity (n,) of ``uv`` by ``unproject`` (pixels (n, 2) ->
        both; e.g. ``LandmarkTriangulator.bearings``), computed on the first call and kept:
        one camera per estimator."""
        if self._bearings is None:
            self._bearings = unproject(self.uv)
        return self._bearings


def shared_tracks(cur: FrameTracks, ref: FrameTracks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracks of ``cur`` that ``ref`` has too, in ``cur``'s order: ``(ids, rows in cur,
    rows in ref)``."""
    in_ref = np.isin(cur.ids, ref.ids, assume_unique=True)
    rows_cur = np.flatnonzero(in_ref)
    common = cur.ids[rows_cur]
    sorter = np.argsort(ref.ids, kind="stable")
    rows_ref = sorter[np.searchsorted(ref.ids, common, sorter=sorter)]
    return common, rows_cur, rows_ref
