"""The frontend's tracks of the frames in the window, as the estimator keeps them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from granite.optical_flow import OpticalFlowResult


@dataclass
class FrameTracks:
    """Tracks of one frame by track id: pixel position ``(u, v)`` and the pyramid level the
    feature was created on. Track ids are the landmark ids of the backend."""

    positions: dict[int, np.ndarray]
    levels: dict[int, int]

    @classmethod
    def from_result(cls, result: OpticalFlowResult) -> FrameTracks:
        ids = result.ids.tolist()
        return cls(dict(zip(ids, result.positions)), dict(zip(ids, result.levels.tolist())))
