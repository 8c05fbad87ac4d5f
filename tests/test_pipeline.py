"""The concurrent frame pipeline (frontend of frame k+1 beside the estimator of frame k) gives
bit-identical results to the sequential loop: trajectories, diagnostics, tracks, records."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from granite.estimator.config import VoConfig
from granite.estimator.pipeline import VoPipeline, opencv_single_threaded
from granite.estimator.runner import run_vo
from granite.estimator.vo import MonocularVO
from granite.io import open_dataset
from granite.optical_flow.tracking import PASS_GUESS, PASS_LOCAL, PASS_MEDIAN, PASS_ZERO, independent_passes

SEQUENCES = Path(__file__).resolve().parents[1] / "assets" / "sequences"
ASSETS = sorted(p.name for p in SEQUENCES.iterdir() if (p / "mav0").is_dir())


def _diagnostics(result) -> list[tuple]:
    """Every diagnostics field but the wall-clock processing time."""
    return [tuple(v for f, v in dataclasses.asdict(d).items() if f != "processing_ms")
            for d in result.diagnostics]


def _same_outputs(a, b) -> None:
    assert np.array_equal(a.trajectory.timestamps, b.trajectory.timestamps)
    assert np.array_equal(a.trajectory.poses, b.trajectory.poses)  # bit for bit
    assert np.array_equal(a.trajectory.submap_ids(), b.trajectory.submap_ids())
    assert _diagnostics(a) == _diagnostics(b)
    assert a.keyframes == b.keyframes
    assert a.skipped == b.skipped
    assert [(k.kind, k.message, k.first_frame, k.count) for k in a.tally.kinds.values()] == \
        [(k.kind, k.message, k.first_frame, k.count) for k in b.tally.kinds.values()]


@pytest.mark.slow
@pytest.mark.parametrize("name", ASSETS)
@pytest.mark.parametrize("mode", ["ours", "after_optimisation", "unguided"])
def test_concurrent_run_is_bit_identical_to_sequential(name, mode):
    """On every pre-rendered asset with our defaults (motion-guided tracking, predictions made
    before the estimator step: the frontend runs a whole estimator step ahead), and on two of
    them with the predictions made after frame k's optimisation (the frontend waits for it) and
    without motion-guided tracking (the reference: a whole estimator step ahead)."""
    if mode != "ours" and name not in ("aggressive", "framedrop"):
        pytest.skip("the other modes are checked on the short and the frame-drop sequence")
    config = VoConfig()
    if mode != "ours":
        change = ({"predict_before_estimate": False} if mode == "after_optimisation"
                  else {"motion_guided_tracking": False})
        config = dataclasses.replace(config, estimator=dataclasses.replace(config.estimator, **change))
    dataset = open_dataset(SEQUENCES / name)
    records = {True: [], False: []}

    def recorder(concurrent):
        def on_frame(frame, out):
            tr = out.tracks
            records[concurrent].append((frame.index, None if tr is None else (tr.ids, tr.positions, tr.levels),
                                        out.track_inverse_distance, out.landmarks_w, out.keyframe_ids))
        return on_frame

    seq = run_vo(dataset, config, progress=False, concurrent=False, on_frame=recorder(False))
    conc = run_vo(dataset, config, progress=False, concurrent=True, on_frame=recorder(True))
    _same_outputs(seq, conc)
    assert len(records[True]) == len(records[False]) == len(seq.diagnostics)
    for (i, ta, da, la, ka), (j, tb, db, lb, kb) in zip(records[False], records[True]):
        assert i == j and ka == kb
        assert (ta is None) == (tb is None)
        if ta is not None:
            assert all(np.array_equal(x, y) for x, y in zip(ta, tb))
        assert np.array_equal(da, db, equal_nan=True)
        assert np.array_equal(la, lb)


@dataclasses.dataclass
class _Frame:
    index: int
    timestamp: float
    image: np.ndarray | None


def test_pipeline_handles_missing_and_rejected_frames_like_the_sequential_loop():
    """Missing images (None), blank frames (rejected by the frontend) and a frame of the wrong
    size in the stream: same outputs and the same warnings, frame by frame."""
    import warnings

    dataset = open_dataset(SEQUENCES / "aggressive")
    images = [f.image for f in dataset.frames(0, 24)]
    images[5] = None
    images[9] = np.full_like(images[9], 7)  # blank
    images[10] = None
    images[14] = images[14][:-2]  # wrong size
    frames = [_Frame(i, float(dataset.timestamps[i]), im) for i, im in enumerate(images)]

    def run(concurrent):
        vo = MonocularVO(dataset.calibration.camera(), VoConfig())
        outputs = VoPipeline(vo, concurrent).run(frames)
        result = []
        while True:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                item = next(outputs, None)
            if item is None:
                return result
            frame, out = item
            result.append((frame.index, out.T_w_c, out.diagnostics.state,
                           sorted(str(w.message) for w in caught)))

    seq, conc = run(False), run(True)
    assert [(i, s, w) for i, _, s, w in seq] == [(i, s, w) for i, _, s, w in conc]
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(seq, conc))
    assert [s for _, _, s, _ in seq].count("skipped") == 4
    assert any("blank image" in m for _, _, _, w in conc for m in w)


def test_opencv_runs_single_threaded_inside_the_pipeline_only():
    """OpenCV's worker pool is off while a concurrent run is in progress (seen from the
    consumer of the frames), also while two runs overlap, and the thread count from before
    is back afterwards, also after an interrupted run."""
    import cv2

    dataset = open_dataset(SEQUENCES / "aggressive")
    frames = list(dataset.frames(0, 6))
    before = cv2.getNumThreads()
    cv2.setNumThreads(3)  # a user's setting, whatever the machine
    try:
        seen = []
        for _ in VoPipeline(MonocularVO(dataset.calibration.camera(), VoConfig()), True).run(frames):
            seen.append(cv2.getNumThreads())
        assert seen == [1] * len(frames) and cv2.getNumThreads() == 3
        for _ in VoPipeline(MonocularVO(dataset.calibration.camera(), VoConfig()), False).run(frames[:2]):
            assert cv2.getNumThreads() == 3  # the sequential loop leaves OpenCV alone
        first, second = opencv_single_threaded(), opencv_single_threaded()
        first.__enter__()
        second.__enter__()  # a second pipeline starts while the first runs ...
        first.__exit__(None, None, None)  # ... and outlives it
        assert cv2.getNumThreads() == 1
        second.__exit__(None, None, None)
        assert cv2.getNumThreads() == 3
        run = VoPipeline(MonocularVO(dataset.calibration.camera(), VoConfig()), True).run(frames)
        next(run)
        run.close()  # the consumer stops early
        assert cv2.getNumThreads() == 3
    finally:
        cv2.setNumThreads(before)


def test_the_split_passes_are_the_per_point_ones():
    order = np.array([PASS_GUESS, PASS_ZERO, PASS_MEDIAN, PASS_LOCAL])
    assert independent_passes(order) == 2
    assert independent_passes(np.array([PASS_ZERO, PASS_MEDIAN])) == 1
    assert independent_passes(np.array([PASS_MEDIAN, PASS_ZERO])) == 0


def test_an_error_in_the_frontend_thread_reaches_the_caller():
    dataset = open_dataset(SEQUENCES / "aggressive")

    class Broken:
        def __iter__(self):
            yield from dataset.frames(0, 3)
            raise RuntimeError("reader failed")

    vo = MonocularVO(dataset.calibration.camera(), VoConfig())
    with pytest.raises(RuntimeError, match="reader failed"):
        for _ in VoPipeline(vo, True).run(Broken()):
            pass


@pytest.mark.parametrize("where", ["estimator", "caller"])
def test_an_interrupted_concurrent_run_keeps_every_finished_frame(where, monkeypatch):
    """The concurrent pipeline hands a frame out once the next one is estimated (its
    Λ_scaledrift runs meanwhile): Ctrl-C inside the estimator or in the caller's own code
    (``on_frame``) still returns every frame finished, equal to the uninterrupted run's."""
    dataset = open_dataset(SEQUENCES / "aggressive")
    full = run_vo(dataset, VoConfig(), progress=False, max_frames=14, concurrent=False)
    original = MonocularVO.estimate

    def estimate(self, frame_id, *args):
        if where == "estimator" and frame_id == 10:
            raise KeyboardInterrupt
        return original(self, frame_id, *args)

    def on_frame(frame, out):
        if where == "caller" and frame.index == 10:
            raise KeyboardInterrupt

    monkeypatch.setattr(MonocularVO, "estimate", estimate)
    result = run_vo(dataset, VoConfig(), progress=False, on_frame=on_frame, max_frames=14,
                    concurrent=True)
    assert result.interrupted
    kept = [d.frame_index for d in result.diagnostics]
    assert kept == list(range(len(kept)))
    # interrupted while estimating frame 10: frames 0-9; in on_frame of frame 10: frame 11 was
    # estimated too (its Λ computing) and is kept
    assert len(kept) == (10 if where == "estimator" else 12)
    assert _diagnostics(result) == _diagnostics(full)[:len(kept)]
    assert np.array_equal(result.trajectory.poses, full.trajectory.poses[:len(result.trajectory)])
