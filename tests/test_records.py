"""``landmarks.npz``: the per-frame records of a run read back as written."""

from __future__ import annotations

import numpy as np

from granite.estimator.records import FrameRecord, RecordWriter, read_records


def _record(rng, index: int, tracks: int, landmarks: int, keyframes: int) -> FrameRecord:
    return FrameRecord(
        index, 0.05 * index + 1e-7 * rng.random(),
        track_ids=rng.integers(0, 10**6, tracks), track_uv=rng.uniform(0, 640, (tracks, 2)),
        track_level=rng.integers(0, 5, tracks), track_inverse_distance=rng.uniform(0, 1, tracks),
        keyframe_ids=tuple(int(k) for k in rng.integers(0, index + 1, keyframes)),
        landmarks_w=rng.normal(size=(landmarks, 3)).astype(np.float32),
        landmarks_inverse_distance=rng.uniform(0, 1, landmarks).astype(np.float32))


def test_records_read_back_frame_by_frame_as_written(tmp_path):
    """Every field of every record (frames with no tracks, landmarks or keyframes among them)
    comes back in order and exactly, the landmarks in float32 as written; also from a file
    whose rows are not grouped by frame."""
    rng = np.random.default_rng(7)
    shapes = [(5, 3, 1), (0, 0, 0), (9, 0, 2), (1, 7, 0), (0, 2, 3), (12, 12, 4)]
    records = [_record(rng, i, *s) for i, s in enumerate(shapes)]
    writer = RecordWriter(tmp_path / "landmarks.npz")
    for r in records:
        writer.append(r)
    writer.close()
    back = read_records(tmp_path / "landmarks.npz")
    assert [r.index for r in back] == [r.index for r in records]
    for a, b in zip(records, back):
        assert a.timestamp == b.timestamp and a.keyframe_ids == b.keyframe_ids
        for name in ("track_ids", "track_uv", "track_level", "track_inverse_distance"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert b.landmarks_w.dtype == np.float32 and b.landmarks_w.shape == (len(a.landmarks_w), 3)
        np.testing.assert_array_equal(a.landmarks_w, b.landmarks_w)
        np.testing.assert_array_equal(a.landmarks_inverse_distance, b.landmarks_inverse_distance)


def test_records_read_back_from_rows_not_grouped_by_frame(tmp_path):
    """A file whose per-frame blocks come in another order (tags not sorted) reads back the
    same records as the writer's order."""
    rng = np.random.default_rng(8)
    records = [_record(rng, i, *s) for i, s in enumerate([(4, 2, 1), (3, 0, 2), (0, 5, 0), (6, 1, 3)])]
    writer = RecordWriter(tmp_path / "landmarks.npz")
    for r in records:
        writer.append(r)
    writer.close()
    with np.load(tmp_path / "landmarks.npz") as data:
        arrays = {name: data[name] for name in data.files}
    for group in ("track", "landmark", "keyframe"):
        tags = arrays[f"{group}_frame"]
        rows = np.concatenate([np.flatnonzero(tags == f) for f in (2, 0, 3, 1)])
        assert not np.all(np.diff(tags[rows]) >= 0)
        for name in arrays:
            if name.startswith(group + "_"):
                arrays[name] = arrays[name][rows]
    np.savez(tmp_path / "shuffled.npz", **arrays)
    for a, b in zip(read_records(tmp_path / "landmarks.npz"), read_records(tmp_path / "shuffled.npz")):
        assert a.index == b.index and a.keyframe_ids == b.keyframe_ids
        for name in ("track_ids", "track_uv", "track_level", "track_inverse_distance",
                     "landmarks_w", "landmarks_inverse_distance"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
