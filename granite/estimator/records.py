"""Per-frame records of a run, kept for visualisation (``landmarks.npz`` in the run folder).

Arrays (flattened over frames, each row tagged with its frame index):

* tracks: ``track_frame``, ``track_id``, ``track_uv`` (K,2) level-0 pixels, ``track_level``,
  ``track_inverse_distance`` (NaN: not a landmark, 0: at infinity);
* window landmarks: ``landmark_frame``, ``landmark_xyz`` (L,3) float32 world points of the VO
  (unaligned), ``landmark_inverse_distance``;
* window keyframes: ``keyframe_frame``, ``keyframe_id``.
"""

from __future__ import annotations

import shutil
import tempfile
import zipfile
import zlib
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
        """From a :class:`granite.estimator.vo.FrameOutput`. The window landmarks are kept as
        float32, as ``landmarks.npz`` stores them (the bulk of a run's records: 1200 frames of
        the spiral hold ~1 M landmark rows)."""
        rec = cls(index, timestamp, keyframe_ids=tuple(out.keyframe_ids),
                  landmarks_w=np.asarray(out.landmarks_w, np.float32),
                  landmarks_inverse_distance=np.asarray(out.landmarks_inverse_distance, np.float32))
        if out.tracks is not None and len(out.tracks):
            rec.track_ids, rec.track_uv = out.tracks.ids, out.tracks.positions
            rec.track_level, rec.track_inverse_distance = out.tracks.levels, out.track_inverse_distance
        return rec


#: The arrays of ``landmarks.npz``: name, dtype, shape of one row.
_FIELDS = (
    ("frame_index", np.int64, ()),
    ("frame_timestamp", np.float64, ()),
    ("track_frame", np.int64, ()),
    ("track_id", np.int64, ()),
    ("track_uv", np.float64, (2,)),
    ("track_level", np.int64, ()),
    ("track_inverse_distance", np.float64, ()),
    ("landmark_frame", np.int64, ()),
    ("landmark_xyz", np.float32, (3,)),
    ("landmark_inverse_distance", np.float32, ()),
    ("keyframe_frame", np.int64, ()),
    ("keyframe_id", np.int64, ()),
)


def _record_arrays(r: FrameRecord) -> dict[str, np.ndarray]:
    """One record's rows of every array of ``landmarks.npz``."""
    return {
        "frame_index": np.array([r.index]),
        "frame_timestamp": np.array([r.timestamp]),
        "track_frame": np.full(len(r.track_ids), r.index),
        "track_id": r.track_ids,
        "track_uv": r.track_uv,
        "track_level": r.track_level,
        "track_inverse_distance": r.track_inverse_distance,
        "landmark_frame": np.full(len(r.landmarks_inverse_distance), r.index),
        "landmark_xyz": r.landmarks_w,
        "landmark_inverse_distance": r.landmarks_inverse_distance,
        "keyframe_frame": np.full(len(r.keyframe_ids), r.index),
        "keyframe_id": np.array(r.keyframe_ids, np.int64),
    }


class RecordWriter:
    """Writes ``landmarks.npz`` without keeping the records in memory: :meth:`append` streams
    each record's rows to temporary files beside ``path`` (the run folder), :meth:`close`
    assembles the compressed npz from them (chunk by chunk) and removes them. Memory stays
    flat in the length of the run; the arrays are those :func:`write_records` writes."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = tempfile.TemporaryDirectory(prefix=f".{self.path.stem}-", dir=self.path.parent)
        folder = Path(self._tmp.name)
        self._files = {name: open(folder / name, "wb") for name, _, _ in _FIELDS}
        self._rows = {name: 0 for name, _, _ in _FIELDS}

    def append(self, record: FrameRecord) -> None:
        arrays = _record_arrays(record)
        for name, dtype, row in _FIELDS:
            a = np.ascontiguousarray(arrays[name], dtype=dtype).reshape((-1,) + row)
            self._files[name].write(a.tobytes())
            self._rows[name] += a.shape[0]

    def discard(self) -> None:
        """Remove the temporary files without writing ``path``."""
        for f in self._files.values():
            f.close()
        self._tmp.cleanup()

    def close(self) -> None:
        """Write ``path`` (atomically) and remove the temporary files."""
        try:
            for f in self._files.values():
                f.close()
            folder = Path(self._tmp.name)
            with atomic_path(self.path) as tmp:
                with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
                    for name, dtype, row in _FIELDS:
                        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                  "fortran_order": False, "shape": (self._rows[name],) + row}
                        with zf.open(name + ".npy", "w", force_zip64=True) as out, \
                                open(folder / name, "rb") as src:
                            np.lib.format.write_array_header_1_0(out, header)
                            shutil.copyfileobj(src, out, 1 << 20)
        finally:
            self._tmp.cleanup()


def write_records(path: str | Path, records: list[FrameRecord]) -> None:
    writer = RecordWriter(path)
    for r in records:
        writer.append(r)
    writer.close()


def _rows_by_frame(tags: np.ndarray) -> dict[int, slice | np.ndarray]:
    """The rows of each frame index in a ``*_frame`` tag array: a slice when the tags are in
    the writer's order (each frame's rows in one block, so the records are views of the
    arrays, no copies), else the row indices in ascending order."""
    order = None if np.all(tags[1:] >= tags[:-1]) else np.argsort(tags, kind="stable")
    frames, starts = np.unique(tags if order is None else tags[order], return_index=True)
    ends = np.append(starts[1:], len(tags))
    return {int(f): slice(a, b) if order is None else order[a:b]
            for f, a, b in zip(frames.tolist(), starts.tolist(), ends.tolist())}


def read_records(path: str | Path) -> list[FrameRecord]:
    """The records of ``landmarks.npz``, their arrays views of the file's (each array is read
    once: an ``NpzFile`` decompresses a member on every access); the landmarks in float32, as
    stored and as :meth:`FrameRecord.from_output` keeps them."""
    path = Path(path)
    try:
        with np.load(path) as data:
            arrays = {name: data[name] for name, _, _ in _FIELDS}
        groups = {key: _rows_by_frame(arrays[tag]) for key, tag in
                  (("track", "track_frame"), ("landmark", "landmark_frame"), ("keyframe", "keyframe_frame"))}
        records = []
        empty = slice(0, 0)
        for f, t in zip(arrays["frame_index"].tolist(), arrays["frame_timestamp"].tolist()):
            tr, lm, kf = (groups[k].get(f, empty) for k in ("track", "landmark", "keyframe"))
            records.append(FrameRecord(
                f, t, arrays["track_id"][tr], arrays["track_uv"][tr], arrays["track_level"][tr],
                arrays["track_inverse_distance"][tr], tuple(arrays["keyframe_id"][kf].tolist()),
                arrays["landmark_xyz"][lm], arrays["landmark_inverse_distance"][lm],
            ))
        return records
    except FileNotFoundError:
        raise InputError("run records not found", path) from None
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as error:
        raise InputError(f"not a granite run records file ({error})", path) from None
