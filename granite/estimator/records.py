"""Per-frame records of a run, kept for visualisation (``landmarks.npz`` in the run folder).

Arrays (flattened over frames, each row tagged with its frame index):

* tracks: ``track_frame``, ``track_id``, ``track_uv`` (K,2) level-0 pixels, ``track_level``,
  ``track_inverse_distance`` (NaN: not a landmark, 0: at infinity);
* window landmarks: ``landmark_frame``, ``landmark_xyz`` (L,3) float32 world points of the VO
  (unaligned), ``landmark_inverse_distance``;
* window keyframes: ``keyframe_frame``, ``keyframe_id``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io import atomic_path


@dataclass
class FrameRecord:
    index: int
    timestamp: float
    track_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    track_level: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track_inverse_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    keyframe_ids: tuple[int, ...] = ()
    landmarks_w: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    landmarks_inverse_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def from_output(cls, index: int, timestamp: float, out) -> FrameRecord:
        """From a :class:`granite.estimator.vo.FrameOutput`."""
        rec = cls(index, timestamp, keyframe_ids=tuple(out.keyframe_ids),
                  landmarks_w=out.landmarks_w, landmarks_inverse_distance=out.landmarks_inverse_distance)
        if out.tracks is not None and len(out.tracks):
            rec.track_ids, rec.track_uv = out.tracks.ids, out.tracks.positions
            rec.track_level, rec.track_inverse_distance = out.tracks.levels, out.track_inverse_distance
        return rec


def write_records(path: str | Path, records: list[FrameRecord]) -> None:
    def cat(name, dtype, shape):
        parts = [np.asarray(getattr(r, name), dtype) for r in records]
        return np.concatenate(parts) if parts else np.zeros(shape, dtype)

    def tag(name):
        return np.concatenate([np.full(len(getattr(r, name)), r.index, np.int64) for r in records]) \
            if records else np.zeros(0, np.int64)

    arrays = {
        "frame_index": np.array([r.index for r in records], np.int64),
        "frame_timestamp": np.array([r.timestamp for r in records], np.float64),
        "track_frame": tag("track_ids"),
        "track_id": cat("track_ids", np.int64, (0,)),
        "track_uv": cat("track_uv", np.float64, (0, 2)).reshape(-1, 2),
        "track_level": cat("track_level", np.int64, (0,)),
        "track_inverse_distance": cat("track_inverse_distance", np.float64, (0,)),
        "landmark_frame": tag("landmarks_inverse_distance"),
        "landmark_xyz": cat("landmarks_w", np.float32, (0, 3)).reshape(-1, 3),
        "landmark_inverse_distance": cat("landmarks_inverse_distance", np.float32, (0,)),
        "keyframe_frame": tag("keyframe_ids"),
        "keyframe_id": np.concatenate([np.array(r.keyframe_ids, np.int64) for r in records])
        if records else np.zeros(0, np.int64),
    }
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as handle:
            np.savez_compressed(handle, **arrays)


def read_records(path: str | Path) -> list[FrameRecord]:
    path = Path(path)
    try:
        data = np.load(path)
        frames = data["frame_index"]
        times = data["frame_timestamp"]
        groups = {}
        for key, tag in (("track", "track_frame"), ("landmark", "landmark_frame"), ("keyframe", "keyframe_frame")):
            order = data[tag]
            groups[key] = {f: np.flatnonzero(order == f) for f in np.unique(order)}
        records = []
        empty = np.zeros(0, np.int64)
        for f, t in zip(frames.tolist(), times.tolist()):
            tr, lm, kf = (groups[k].get(f, empty) for k in ("track", "landmark", "keyframe"))
            records.append(FrameRecord(
                f, t, data["track_id"][tr], data["track_uv"][tr], data["track_level"][tr],
                data["track_inverse_distance"][tr], tuple(data["keyframe_id"][kf].tolist()),
                data["landmark_xyz"][lm].astype(np.float64), data["landmark_inverse_distance"][lm].astype(np.float64),
            ))
        return records
    except FileNotFoundError:
        raise InputError("run records not found", path) from None
    except (KeyError, ValueError, OSError) as error:
        raise InputError(f"not a granite run records file ({error})", path) from None
