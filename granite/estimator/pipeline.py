"""Drive :class:`~granite.estimator.vo.MonocularVO` over a stream of frames, sequentially or with
the frontend concurrent to the estimator (two cores), with bit-identical results.

What flows between frontend and estimator: the frontend's tracks of frame k go to the estimator;
the only feedback is motion-guided tracking (``[estimator] motion_guided_tracking``, ours, on by
default): frame k+1 is tracked from positions predicted from frame k's tracks, a pose for frame
k, the constant-velocity motion and the window's landmark depths. The reference (feedback off)
runs its optical flow in a thread of its own that feeds the estimator through a queue.

The concurrent pipeline (``concurrent=True``) has three helper threads besides the caller's:

* the **reader** decodes frame k+1 (and k+2: a queue of ``prefetch`` frames) and builds its
  image pyramid and noise estimate (:meth:`FrameToFrameOpticalFlow.prepare
  <granite.optical_flow.FrameToFrameOpticalFlow.prepare>`, OpenCV and GIL-free numba kernels)
  while the estimator works on frame k;
* the **tracker** tracks the points into frame k+1 and detects new corners
  (:class:`~granite.optical_flow.frame_to_frame.FlowJob`), and computes frame k's
  Λ_scaledrift (:func:`granite.backend.scale_drift_task`: the window is copied on the
  caller's thread at the point of the sequential computation, the linearisation, landmark
  elimination and eigen-solver run on the copy with GIL-free kernels) between the tracking of
  frame k+1 and that of frame k+2, while the caller goes on with frame k+1. Frame k's output
  is yielded once frame k+1 is estimated (or at the end, or before a skipped frame): the
  outputs lag the input by one frame; a run stopped early (Ctrl-C) gets the frame held back
  from :meth:`VoPipeline.drain`. Nothing the estimator reads comes from Λ, so the results are
  those of the sequential loop; the frame's warnings are recorded and issued with its output.
  Λ runs on the tracker's thread, not on a thread of its own: with a fourth busy thread on two
  cores the operating system's fair share took CPU time from the caller's thread, which is
  the critical path: in paired measurements on the 640x480 spiral the fourth thread made it
  up to 12 % slower (median wall ratios 0.88-1.01, docs/architecture.md, twenty-third session);
* the **helper**, which joins the points' guided / zero-motion passes (the kernel is per point
  independent there; the median and local passes follow over all points) when the tracking
  was started while the caller waits for it.

Work sharing: those per-point passes run in chunks of points that any thread claims through
an atomic counter inside the GIL-free kernel (:mod:`granite.optical_flow.work_share`). The
caller's thread, once it has finished frame k and waits for frame k+1's tracks, claims the
chunks left (:meth:`FlowJob.wait <granite.optical_flow.frame_to_frame.FlowJob.wait>`), so
the second core is not idle whichever of tracking and estimation is the longer.

The tracking of frame k+1 starts as soon as its inputs exist: without motion-guided tracking,
and with it when the predictions are made before the estimator step (``[estimator]
predict_before_estimate``, the default), right after frame k's tracks are known
(:meth:`MonocularVO.note_tracks`), so it overlaps the whole estimator of frame k as in the
reference (on the tracker thread, joined by the caller when it is done with frame k); with ``predict_before_estimate
= false`` once frame k's pose and landmarks are optimised (:meth:`MonocularVO.estimate` calls
back before Λ_scaledrift and marginalisation), so it overlaps the rest of frame k and
:meth:`MonocularVO.finish`, shared with the helper thread from the start. Every piece of
state is written by one thread at a time in the sequential order of the operations, and every
computation gets the same inputs as in the sequential mode, so trajectories, diagnostics and
tracks are bit-identical (``tests/test_pipeline.py``); ``concurrent=False`` (``granite run
--sequential``) is the plain loop over :meth:`MonocularVO.process`, kept for debugging.

OpenCV's own thread pool is switched off while the pipeline runs (``cv2.setNumThreads(1)``,
restored afterwards; :func:`opencv_single_threaded`): the pipeline's threads already keep both
cores busy, and OpenCV's worker, woken by each pyramid, blur or corner detection call,
spins on ``sched_yield`` after its share of the call (about 1 ms of CPU per spiral frame,
most of it system time). Paired in one process on the 640x480 spiral, 8 rounds: wall time ratio 0.951
(6 of 8 rounds faster), CPU time 0.925 (docs/architecture.md, twenty-fourth session). Results
do not depend on it (OpenCV's parallel loops split rows; ``tests/test_pipeline.py``).

Warnings: the caller (``runner.run_vo``) records the warnings raised while it waits for each
frame's output (the pipeline records each frame's own and issues them with its output). The
frontend work started early for frame k+1 on the caller's thread (its prediction and guesses)
records its warnings and re-issues them with frame k+1; the helper threads run only numba
kernels, OpenCV and small numpy operations, which issue none, and Λ_scaledrift runs with
numpy's floating-point warnings off.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import cv2
from threadpoolctl import threadpool_limits

from granite.estimator.vo import FrameOutput, MonocularVO

_END = object()


class _Failure:
    def __init__(self, error: BaseException):
        self.error = error


def _reissue(caught: list[warnings.WarningMessage]) -> None:
    """Issue recorded warnings again (on the caller's thread, with their own source line)."""
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)


class VoPipeline:
    """``run(frames)`` yields ``(frame, FrameOutput)`` per frame; a frame is anything with
    ``index``, ``timestamp`` and ``image`` (None: missing or unreadable) attributes, e.g.
    :class:`granite.io.Frame`."""

    def __init__(self, vo: MonocularVO, concurrent: bool = True, prefetch: int = 2):
        self.vo = vo
        self.concurrent = concurrent
        self.prefetch = max(1, int(prefetch))
        #: wall seconds the caller's thread waited for the reader, for the tracker and for the
        #: previous frame's Λ_scaledrift (``waited_scale_drift``), and
        #: its CPU seconds (``time.thread_time``) inside :meth:`run` (concurrent mode)
        self.waited_reader = 0.0
        self.waited_tracker = 0.0
        self.waited_scale_drift = 0.0
        self.caller_cpu = 0.0
        #: (frame, output, warnings) of the frame whose Λ_scaledrift is computing (concurrent)
        self._held: list = []

    def drain(self) -> list[tuple[object, FrameOutput, list[warnings.WarningMessage]]]:
        """After :meth:`run` stopped early (an exception inside it, e.g. Ctrl-C, or the
        caller closing it): the frame it had finished but not yet yielded (its Λ_scaledrift
        was computing), completed, with the warnings recorded while it was processed; empty
        when there is none (the sequential mode never holds a frame back)."""
        out = [(frame, self.vo.complete(o), caught) for frame, o, caught in self._held]
        self._held.clear()
        return out

    def run(self, frames: Iterable) -> Iterator[tuple[object, FrameOutput]]:
        """Process ``frames`` (both modes with BLAS on one thread: :func:`blas_single_threaded`)."""
        with blas_single_threaded():
            if not self.concurrent:
                vo = self.vo
                for frame in frames:
                    yield frame, vo.process(frame.index, frame.timestamp, frame.image)
                return
            yield from self._run_concurrent(frames)

    # ------------------------------------------------------------------ concurrent
    def _reader(self, frames: Iterable, out: queue.Queue, stop: threading.Event) -> None:
        flow = self.vo.flow
        try:
            for frame in frames:
                prep = None if frame.image is None else flow.prepare(frame.image)
                while not stop.is_set():
                    try:
                        out.put((frame, prep), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            item = _END
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            item = _Failure(exc)
        while not stop.is_set():
            try:
                out.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _run_concurrent(self, frames: Iterable) -> Iterator[tuple[object, FrameOutput]]:
        with opencv_single_threaded():
            yield from self._run_concurrent_threads(frames)

    def _run_concurrent_threads(self, frames: Iterable) -> Iterator[tuple[object, FrameOutput]]:
        vo, flow = self.vo, self.vo.flow
        waits = vo.next_tracking_waits_for_estimate
        items: queue.Queue = queue.Queue(maxsize=self.prefetch)
        stop = threading.Event()
        reader = threading.Thread(target=self._reader, args=(frames, items, stop),
                                  name="granite-reader", daemon=True)
        tracker = ThreadPoolExecutor(1, thread_name_prefix="granite-tracker")
        helper = ThreadPoolExecutor(1, thread_name_prefix="granite-helper")
        vo.scale_drift_executor = tracker  # Λ_scaledrift between two trackings (module docstring)
        # the helper joins the tracking of a frame begun early only while the caller waits for
        # it; when the whole estimator step runs meanwhile, the caller joins at its end
        early_helper = helper if waits else None

        def take():
            t = time.perf_counter()
            item = items.get()
            self.waited_reader += time.perf_counter() - t
            if isinstance(item, _Failure):
                raise item.error
            return item

        def launch(item):
            """Begin the frontend of the frame ``item`` now, on the caller's thread (its
            warnings kept for that frame), and run its tracking on the tracker thread."""
            frame, prep = item
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                job = flow.begin(frame.timestamp, prep, vo.predict_tracks(frame.timestamp), early_helper,
                                 share_points=True)
            if job.rejected is None:
                tracker.submit(job.run)
            return frame, job, caught

        held = self._held  # (frame, output, warnings) of the last frame, its Λ computing
        held.clear()

        def release():
            """The held frame's finished output (waits for its Λ_scaledrift), its warnings
            re-issued; None if no frame is held."""
            if not held:
                return None
            frame, out, caught = held[0]
            t = time.perf_counter()
            out = vo.complete(out)
            self.waited_scale_drift += time.perf_counter() - t
            held.clear()  # only once complete: an interruption while waiting leaves it to drain()
            _reissue(caught)
            return frame, out

        reader.start()
        pending = None  # (frame, job, warnings) of the next frame, begun early
        cpu = time.thread_time()
        try:
            item = take()
            while item is not _END:
                frame, prep = item
                start = time.perf_counter()
                if frame.image is None:  # skipped: changes no state
                    out = vo.process(frame.index, frame.timestamp, None)
                    item = take()
                    self.caller_cpu += time.thread_time() - cpu
                    done = release()
                    if done is not None:
                        yield done
                    yield frame, out
                    cpu = time.thread_time()
                    continue
                # the frame's warnings, issued when its output is (after its Λ_scaledrift)
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    if pending is not None and pending[0] is frame:
                        _, job, early = pending
                        _reissue(early)
                    else:
                        job = flow.begin(frame.timestamp, prep, vo.predict_tracks(frame.timestamp),
                                         helper, share_points=True)
                        job.run()
                    pending = None
                    t = time.perf_counter()
                    job.wait()
                    self.waited_tracker += time.perf_counter() - t
                    tracks = flow.complete(job)
                    vo.note_tracks(frame.timestamp, tracks)
                    nxt = take()
                    launch_next = nxt is not _END and nxt[0].image is not None
                    launched = []
                    if launch_next and not waits:  # the next frame needs nothing of this estimate
                        pending = launch(nxt)
                    ready = (lambda: launched.append(launch(nxt))) if launch_next and waits else None
                    estimated = vo.estimate(frame.index, frame.timestamp, frame.image, tracks, start,
                                            ready)
                    if ready is not None:  # launched once the predictions were fixed (or now)
                        pending = launched[0] if launched else launch(nxt)
                    out = vo.finish(estimated)
                # this frame's Λ_scaledrift runs while the estimator works on the next frame:
                # its output is yielded after the next frame's estimate (or at the end)
                done = release()
                held.append((frame, out, caught))
                self.caller_cpu += time.thread_time() - cpu
                if done is not None:
                    yield done
                cpu = time.thread_time()
                item = nxt
            done = release()
            if done is not None:
                yield done
        finally:
            stop.set()
            if pending is not None and pending[1].rejected is None:
                try:
                    pending[1].wait()
                except BaseException:  # noqa: BLE001 - the frame is abandoned anyway
                    pass
            tracker.shutdown(wait=True)
            helper.shutdown(wait=True)
            vo.scale_drift_executor = None
            try:  # unblock the reader
                while True:
                    items.get_nowait()
            except queue.Empty:
                pass
            reader.join(timeout=5.0)


class _ProcessWideSetting:
    """A process-wide setting held while at least one block is open: ``apply()`` sets it and
    returns the callable that restores what was there before. Overlapping blocks (two
    pipelines in two threads) share it; the state from before the first block is restored when
    the last one ends."""

    def __init__(self, apply: Callable[[], Callable[[], object]]):
        self._apply = apply
        self._lock = threading.Lock()
        self._users = 0  # blocks open now, in any thread
        self._restore: Callable[[], object] | None = None

    @contextlib.contextmanager
    def __call__(self):
        with self._lock:
            if self._users == 0:
                self._restore = self._apply()
            self._users += 1
        try:
            yield
        finally:
            with self._lock:
                self._users -= 1
                if self._users == 0:
                    self._restore()
                    self._restore = None


def _opencv_on_one_thread() -> Callable[[], None]:
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    return lambda: cv2.setNumThreads(previous)


def _blas_on_one_thread() -> Callable[[], object]:
    return threadpool_limits(limits=1, user_api="blas").restore_original_limits


#: ``with opencv_single_threaded():`` OpenCV's parallel loops run on the calling thread inside
#: the block (its worker pool off); process-wide (:class:`_ProcessWideSetting`).
opencv_single_threaded = _ProcessWideSetting(_opencv_on_one_thread)

#: ``with blas_single_threaded():`` the BLAS libraries loaded (numpy's and scipy's OpenBLAS)
#: use one thread inside the block; process-wide (:class:`_ProcessWideSetting`). The VO's
#: matrices are small (at most a few hundred rows): with a second BLAS thread spinning beside
#: the pipeline's threads, the 640x480 spiral ran at 29 frames/s through the Python API
#: against 57-64 with one (``granite``'s command line sets ``OPENBLAS_NUM_THREADS=1`` before
#: numpy loads; a script or notebook that imported numpy first did not get it).
blas_single_threaded = _ProcessWideSetting(_blas_on_one_thread)
