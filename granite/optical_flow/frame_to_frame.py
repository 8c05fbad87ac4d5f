"""Frame-to-frame KLT optical flow with multi-level FAST detection (paper Sec. IV-A).

Each call of :meth:`FrameToFrameOpticalFlow.process` tracks the points of the previous
accepted frame into the new one (coarse to fine, forward-backward checked), then detects new
corners in the free grid cells. Points are patch centres in level-0 pixels; the centre of the
top-left pixel is (0, 0). Track ids are persistent and never reused.

A frame that cannot be used (``None``, not a 2-D uint8/uint16 array, a size different from
the first frame's, or a constant image) gives a :class:`FrameRejectedWarning` and an empty
result; the tracker keeps the last accepted frame, so the next good frame is tracked from it
(as across a frame drop).

Motion-guided tracking: the caller (the VO) may pass predicted positions of existing tracks in
the new image (``process(..., predicted=(ids, positions))``); those tracks are first tracked
coarse to fine from the predicted displacement, and fall back to the unguided passes when that
fails the forward-backward check. Without a prediction the behaviour is the reference one.
"""

from __future__ import annotations

import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from granite.optical_flow.config import OpticalFlowConfig
from granite.optical_flow.detection import detect_new_points
from granite.optical_flow.global_motion import homography_guess, image_homography
from granite.optical_flow.noise import estimate_noise, level_noise_gains
from granite.optical_flow.patterns import make_pattern
from granite.optical_flow.work_share import PointShare
from granite.optical_flow.pyramid import SUPPORTED_DTYPES, ImagePyramid, build_pyramid
from granite.optical_flow.probe import corrected_guess, prediction_correction, probe_indices
from granite.optical_flow.tracking import PASS_GUESS, new_template_cache, pass_order, track_points


class FrameRejectedWarning(UserWarning):
    """An input frame was unusable; the frontend returned zero tracks for it."""


@dataclass(frozen=True)
class OpticalFlowResult:
    """Tracks of one frame.

    Attributes:
        timestamp: seconds.
        ids: (N,) int64 persistent track ids, ascending.
        positions: (N, 2) float64 patch centres (u, v) in level-0 pixels.
        levels: (N,) int64 creation level c of each patch.
        weights: (N,) float64 observation weights 1 / 2**c (paper Eq. 7).
        angles: (N,) float64 patch rotation (rad) accumulated since creation (SE(2) warp).
        new: (N,) bool, True for points detected in this frame.
        timing: milliseconds per stage: ``pyramid``, ``tracking``, ``detection``, ``total``.
        rejected: why the frame was rejected (then N = 0), else None.
    """

    timestamp: float
    ids: np.ndarray
    positions: np.ndarray
    levels: np.ndarray
    weights: np.ndarray
    angles: np.ndarray
    new: np.ndarray
    timing: dict[str, float] = field(default_factory=dict)
    rejected: str | None = None

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True)
class PreparedImage:
    """What :meth:`FrameToFrameOpticalFlow.prepare` computes from an image alone."""

    image: np.ndarray | None
    pyramid: ImagePyramid | None
    noise: float
    #: the image is not a 2-D uint8 / uint16 array (why), else None
    rejected: str | None
    blank: bool
    ms: float
    #: the detection levels as 8-bit images (:meth:`ImagePyramid.level_uint8`), made ahead of
    #: time with the pyramid (off the critical path between two frames' tracking)
    images_u8: dict[int, np.ndarray] | None = None


class FlowJob:
    """The tracking and detection of one frame (:meth:`FrameToFrameOpticalFlow.begin`): pure
    work on arrays that no one else writes until :meth:`FrameToFrameOpticalFlow.complete`.
    :meth:`run` does it (in any thread, once: the first caller); :meth:`wait` returns when it
    is done (running it itself when no thread has started it, otherwise claiming what is left
    of the tracking's per-point passes, :attr:`share`)."""

    def __init__(self, timestamp: float, prepared: PreparedImage, rejected: str | None):
        self.timestamp = timestamp
        self.prepared = prepared
        self.rejected = rejected
        self.track = None
        self.cache = None
        self.inputs = None
        self.config = None
        self.output = None
        self.rows = None
        #: the tracking's per-point passes, which a waiting thread may join (:meth:`wait`), or
        #: None (``begin(..., share_points=False)``)
        self.share: PointShare | None = None
        self.timing: dict[str, float] = {}
        self._done = threading.Event()
        self._error: BaseException | None = None
        self._claim = threading.Lock()  # held by the thread that runs the job

    def run(self) -> None:
        if self.rejected is not None or not self._claim.acquire(blocking=False):
            return  # nothing to do, or done / being done by another thread
        try:
            t1 = time.perf_counter()
            ids, points, levels, angles = self.inputs
            if self.track is not None:
                new_points, dtheta, status = self.track()
                ids, points, levels = ids[status], new_points[status], levels[status]
                angles = angles[status] + dtheta[status]
                self.rows = np.flatnonzero(status)
                if self.config.max_tracks_per_cell > 0:
                    keep = crowded_tracks_kept(ids, points, levels, self.config.grid_size,
                                               self.config.max_tracks_per_cell)
                    ids, points, levels, angles = ids[keep], points[keep], levels[keep], angles[keep]
                    self.rows = self.rows[keep]
            else:
                ids, points, levels, angles = ids[:0], points[:0], levels[:0], angles[:0]
                self.rows = np.zeros(0, dtype=np.int64)
            t2 = time.perf_counter()
            det_points, det_levels = detect_new_points(self.prepared.pyramid, self.config, points, levels,
                                                       self.prepared.images_u8)
            t3 = time.perf_counter()
            self.output = (ids, points, levels, angles, det_points, det_levels)
            self.timing = {"tracking": 1e3 * (t2 - t1), "detection": 1e3 * (t3 - t2)}
        except BaseException as exc:  # re-raised by wait() in the caller's thread
            self._error = exc
        finally:
            if self.share is not None:
                self.share.close()
            self._done.set()

    def wait(self) -> None:
        if self.rejected is not None:
            return
        self.run()  # here, unless a thread has taken it already
        if self.share is not None:
            self.share.help()  # claims what is left of the tracking's per-point passes
        self._done.wait()
        if self._error is not None:
            raise self._error


class FrameToFrameOpticalFlow:
    """The frontend. ``image_size`` = (width, height); if None, the first accepted frame sets it."""

    def __init__(self, config: OpticalFlowConfig | None = None, image_size: tuple[int, int] | None = None):
        self.config = config or OpticalFlowConfig()
        self.image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        self._pattern = make_pattern(self.config.pattern, self.config.pattern_scale)
        coarse = self.config.coarse_pattern
        self._pattern_coarse = (self._pattern if coarse == "same"
                                else make_pattern(coarse, self.config.pattern_scale))
        self._pyramid: ImagePyramid | None = None
        self._image_u8: np.ndarray | None = None  # level 0 of the reference frame, 8 bits
        self._ids = np.zeros(0, dtype=np.int64)
        self._points = np.zeros((0, 2))
        self._levels = np.zeros(0, dtype=np.int64)
        self._angles = np.zeros(0)
        self._next_id = 0
        # Templates of the current points in the reference image (filled by the backward pass
        # of the last frame) and each point's row in it (-1: none).
        self._cache = new_template_cache(0, self.config.levels, len(self._pattern))
        self._rows = np.zeros(0, dtype=np.int64)
        self._storage: list[tuple[np.ndarray, ...] | None] = [None, None]
        self._active = 0
        self._noise: float = 0.0  # noise sigma of the reference frame (input units)
        self._needs_noise = self.config.fb_noise_factor > 0.0
        self._gains = np.asarray(level_noise_gains(self.config.levels, self.config.presmooth_sigma))

    @property
    def next_id(self) -> int:
        """The id the next new track gets (= number of ids issued so far)."""
        return self._next_id

    def current_tracks(self) -> tuple[np.ndarray, np.ndarray]:
        """Ids (N,) and level-0 positions (N, 2) of the tracks in the last accepted frame
        (copies); the ids a ``predicted`` argument of :meth:`process` refers to."""
        return self._ids.copy(), self._points.copy()

    def reset(self) -> None:
        """Forget all tracks and the reference frame (ids keep increasing)."""
        self._pyramid = None
        self._image_u8 = None
        self._ids = np.zeros(0, dtype=np.int64)
        self._points = np.zeros((0, 2))
        self._levels = np.zeros(0, dtype=np.int64)
        self._angles = np.zeros(0)
        self._cache = new_template_cache(0, self.config.levels, len(self._pattern))
        self._rows = np.zeros(0, dtype=np.int64)

    def prepare(self, image: np.ndarray | None) -> PreparedImage:
        """The part of :meth:`process` that depends on the image alone: type and blank checks,
        the pyramid and the noise estimate. Reads no tracker state, so it may run ahead of
        time in another thread (the pyramid and noise kernels release the GIL)."""
        t0 = time.perf_counter()
        reason = self._check_type(image)
        if reason is not None:
            return PreparedImage(image, None, 0.0, reason, False, 0.0)
        assert image is not None
        blank = image.size == 0 or bool(image.min() == image.max())
        if blank:
            return PreparedImage(image, None, 0.0, None, True, 0.0)
        cfg = self.config
        pyramid = build_pyramid(image, cfg.levels, cfg.presmooth_sigma)
        noise = estimate_noise(image, stride=4) if self._needs_noise else 0.0
        images_u8 = {lvl: pyramid.level_uint8(lvl) for lvl in cfg.detection_levels
                     if lvl < pyramid.num_levels}
        return PreparedImage(image, pyramid, noise, None, False, 1e3 * (time.perf_counter() - t0),
                             images_u8)

    def process(
        self,
        timestamp: float,
        image: np.ndarray | None,
        predicted: tuple[np.ndarray, np.ndarray] | None = None,
        prepared: PreparedImage | None = None,
        executor=None,
    ) -> OpticalFlowResult:
        """Track into ``image`` (2-D uint8 or uint16) and detect new points.

        ``predicted`` = ``(track_ids (K,), positions (K, 2))``: optional predicted positions
        (level-0 pixels in ``image``) of some or all current tracks, i.e. the ids of the last
        accepted frame's result. Ids not currently tracked and rows with non-finite positions
        are ignored. A track with a prediction is first tracked from the predicted
        displacement (forward from ``p + g``, back from the found ``p'`` starting at
        ``p' - g``, same forward-backward check, plus a patch correlation of at least
        ``config.guess_min_zncc``); if that fails it is tracked as without a prediction
        (zero motion, then the median-flow retry). ``None`` (or K = 0) gives the unguided
        result, bit for bit.

        ``prepared``: :meth:`prepare` of ``image``, when done already. ``executor``: a
        ``concurrent.futures`` executor with a free worker, which joins the tracking's
        per-point passes (bit-identical results). ``process`` = :meth:`begin` then
        :meth:`complete`.
        """
        job = self.begin(timestamp, image if prepared is None else prepared, predicted, executor)
        job.run()
        return self.complete(job)

    def begin(self, timestamp: float, image, predicted=None, executor=None,
              share_points: bool = False) -> FlowJob:
        """The first half of :meth:`process`: the checks that need the tracker (image size),
        the guesses and the inputs of the tracking. ``image``: an image or its
        :class:`PreparedImage`. The returned job's :meth:`FlowJob.run` (tracking and detection:
        numba kernels and OpenCV, no tracker state) may then run in another thread while the
        caller works on other data; :meth:`complete` must follow before the next ``begin``
        (it waits for ``run``). With ``share_points`` a thread that waits for the job
        (:meth:`FlowJob.wait`) meanwhile joins the tracking's per-point passes (same results).
        Nothing of the tracker changes before :meth:`complete`, except the choice of the
        template storage the job writes."""
        prep = image if isinstance(image, PreparedImage) else self.prepare(image)
        reason = prep.rejected
        if reason is None and self.image_size is not None:
            h, w = prep.image.shape
            if (w, h) != self.image_size:
                reason = f"image size {w}x{h} differs from {self.image_size[0]}x{self.image_size[1]}"
        if reason is None and prep.blank:
            reason = "blank image (constant intensity)"
        if reason is not None:
            return FlowJob(float(timestamp), prep, reason)
        if self.image_size is None:
            self.image_size = (prep.image.shape[1], prep.image.shape[0])
        cfg = self.config
        job = FlowJob(float(timestamp), prep, None)
        if share_points:
            job.share = PointShare()
        ids = self._ids
        job.cache = self._take_cache(len(ids))
        if self._pyramid is not None and len(ids):
            guess = self._guess(predicted)
            fb_var = None
            if cfg.fb_noise_factor > 0.0:
                fb_var = cfg.fb_noise_factor**2 * (self._noise**2 + prep.noise**2) * self._gains**2
            prev, pyramid = self._pyramid, prep.pyramid
            points, levels, rows, cache_a, cache_b = self._points, self._levels, self._rows, self._cache, job.cache
            share = job.share  # not the job itself: no reference cycle keeping its arrays alive

            prev_u8 = self._image_u8  # None with the global retry off
            cur_u8 = _level0_u8(prep) if prev_u8 is not None else None

            def track():
                common = dict(min_zncc_guess=cfg.guess_min_zncc, local_neighbours=cfg.local_retry_neighbours,
                              fb_var=fb_var, fb_max_sq=cfg.fb_max_sq,
                              guided_levels_above=cfg.guided_levels_above, pattern_coarse=self._pattern_coarse)
                images = (prev.data, prev.offsets, prev.widths, prev.heights,
                          pyramid.data, pyramid.offsets, pyramid.widths, pyramid.heights)
                tail = (self._pattern, cfg.margin, cfg.iterations, cfg.fb_threshold_sq, cfg.retry_min_flow)
                order = pass_order(guess is not None, cfg.local_retry_rounds, cfg.guided_levels_above >= 0,
                                   near_after_fine=cfg.guided_levels_above == 0)
                guesses, preset, fallback = guess, None, None
                if guess is not None and cfg.probe_points > 0:
                    guesses, preset, confirmed = _probe(images, points, levels, rows, cache_a, cache_b, tail,
                                                        guess, order, cfg.probe_points, common)
                    if confirmed and not cfg.retry_out_of_view:
                        fallback = ~predicted_out_of_view(points + guesses, pyramid.widths[0],
                                                          pyramid.heights[0])
                result = track_points(
                    *images, points, levels, rows, *cache_a, *cache_b, *tail,
                    guess=guesses, order=order, executor=executor, share=share, preset=preset,
                    fallback=fallback, **common,
                )
                lost = ~result[2]
                if (cfg.global_retry_min_lost > 0.0 and prev_u8 is not None and len(lost) >= _GLOBAL_RETRY_MIN_POINTS
                        and lost.sum() >= cfg.global_retry_min_lost * len(lost)):
                    _global_retry(result, lost, prev_u8, cur_u8, images, points, levels, rows, cache_a,
                                  cache_b, tail, common)
                return result
            job.track = track
        job.inputs = (self._ids, self._points, self._levels, self._angles)
        job.config = cfg
        return job

    def complete(self, job: FlowJob) -> OpticalFlowResult:
        """The second half of :meth:`process`: wait for the job's tracking and detection, then
        update the tracker and return the frame's result (warns on a rejected frame)."""
        if job.rejected is not None:
            warnings.warn(f"frame at t={job.timestamp:.6f}: {job.rejected}; no tracks",
                          FrameRejectedWarning, stacklevel=3)
            return self._empty(job.timestamp, job.rejected)
        job.wait()
        ids, points, levels, angles, det_points, det_levels = job.output
        n_new = len(det_points)
        det_ids = np.arange(self._next_id, self._next_id + n_new, dtype=np.int64)
        self._next_id += n_new
        self._pyramid = job.prepared.pyramid
        self._image_u8 = _level0_u8(job.prepared) if self.config.global_retry_min_lost > 0.0 else None
        self._noise = job.prepared.noise
        self._cache = job.cache
        self._rows = np.concatenate([job.rows, np.full(n_new, -1, dtype=np.int64)])
        self._ids = np.concatenate([ids, det_ids])
        self._points = np.concatenate([points, det_points])
        self._levels = np.concatenate([levels, det_levels])
        self._angles = np.concatenate([angles, np.zeros(n_new)])
        new = np.zeros(len(self._ids), dtype=bool)
        new[len(ids):] = True
        timing = {"pyramid": job.prepared.ms, **job.timing}
        timing["total"] = timing["pyramid"] + timing["tracking"] + timing["detection"]
        return OpticalFlowResult(
            timestamp=job.timestamp,
            ids=self._ids.copy(),
            positions=self._points.copy(),
            levels=self._levels.copy(),
            weights=1.0 / np.exp2(self._levels.astype(np.float64)),
            angles=self._angles.copy(),
            new=new,
            timing=timing,
        )

    def _guess(self, predicted) -> np.ndarray | None:
        """Per-track predicted displacement (N, 2) (NaN rows: none), or None without any."""
        if predicted is None:
            return None
        try:
            pred_ids, pred_pos = predicted
        except (TypeError, ValueError):
            raise ValueError("predicted must be a pair (track_ids (K,), positions (K, 2))") from None
        pred_ids = np.asarray(pred_ids).reshape(-1).astype(np.int64)
        pred_pos = np.asarray(pred_pos, dtype=np.float64)
        if pred_pos.shape != (len(pred_ids), 2):
            raise ValueError(
                f"predicted positions must have shape ({len(pred_ids)}, 2), got {pred_pos.shape}"
            )
        if not len(pred_ids) or not len(self._ids):
            return None
        rows = np.searchsorted(self._ids, pred_ids)  # self._ids is ascending
        rows_c = np.minimum(rows, len(self._ids) - 1)
        use = (self._ids[rows_c] == pred_ids) & np.isfinite(pred_pos).all(axis=1)
        if not use.any():
            return None
        guess = np.full((len(self._ids), 2), np.nan)
        guess[rows_c[use]] = pred_pos[use] - self._points[rows_c[use]]
        return guess

    def _take_cache(self, n: int) -> tuple[np.ndarray, ...]:
        """A template cache with n rows marked empty. Two storages alternate (the current
        cache is read while the next one is written) and are kept across frames, which
        avoids page faults on fresh multi-megabyte allocations every frame."""
        self._active = 1 - self._active
        storage = self._storage[self._active]
        if storage is None or storage[0].shape[0] < n:
            capacity = max(64, n + n // 4)
            storage = new_template_cache(capacity, self.config.levels, len(self._pattern))
            self._storage[self._active] = storage
        cache = tuple(a[:n] for a in storage)
        cache[0][:] = -1
        return cache

    @staticmethod
    def _check_type(image: np.ndarray | None) -> str | None:
        if image is None:
            return "no image"
        if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype not in SUPPORTED_DTYPES:
            shape = getattr(image, "shape", None)
            dtype = getattr(image, "dtype", type(image).__name__)
            return f"expected a 2-D uint8 or uint16 image, got {dtype} with shape {shape}"
        return None

    def _empty(self, timestamp: float, reason: str) -> OpticalFlowResult:
        return OpticalFlowResult(
            timestamp=float(timestamp),
            ids=np.zeros(0, dtype=np.int64),
            positions=np.zeros((0, 2)),
            levels=np.zeros(0, dtype=np.int64),
            weights=np.zeros(0),
            angles=np.zeros(0),
            new=np.zeros(0, dtype=bool),
            timing={"pyramid": 0.0, "tracking": 0.0, "detection": 0.0, "total": 0.0},
            rejected=reason,
        )


def crowded_tracks_kept(ids: np.ndarray, points: np.ndarray, levels: np.ndarray, grid_size: int,
                        max_per_cell: int) -> np.ndarray:
    """Boolean mask keeping, in every detection cell of every creation level (``grid_size``
    pixels of that level; positions in level-0 pixels), the ``max_per_cell`` oldest tracks
    (smallest ids): tracks pile up in cells when the image contracts (climbing, zooming out),
    and the extra ones repeat their neighbours' information at full cost."""
    n = len(ids)
    if n == 0:
        return np.ones(0, dtype=bool)
    scale = np.exp2(-levels.astype(np.float64))[:, None] / grid_size
    cells = np.floor(points * scale).astype(np.int64)
    order = np.lexsort((ids, cells[:, 1], cells[:, 0], levels))
    key = np.stack([levels[order], cells[order, 0], cells[order, 1]], axis=1)
    start = np.r_[True, np.any(key[1:] != key[:-1], axis=1)]
    group_start = np.maximum.accumulate(np.where(start, np.arange(n), 0))
    rank = np.arange(n) - group_start
    keep = np.zeros(n, dtype=bool)
    keep[order[rank < max_per_cell]] = True
    return keep


#: The global retry needs at least this many points in the reference frame.
_GLOBAL_RETRY_MIN_POINTS = 20


def _level0_u8(prep: PreparedImage) -> np.ndarray:
    """Level 0 of a prepared image's pyramid as 8 bits (made ahead of time for the detection)."""
    if prep.images_u8 is not None and 0 in prep.images_u8:
        return prep.images_u8[0]
    return prep.pyramid.level_uint8(0)


def predicted_out_of_view(predicted: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: the predicted level-0 positions (N, 2) outside the image (pixel centres
    ``0 .. width - 1``, ``0 .. height - 1``): tracks that left the view. A row without a
    prediction (NaN) is not out of view."""
    x, y = predicted[:, 0], predicted[:, 1]
    return (x < 0.0) | (y < 0.0) | (x > width - 1) | (y > height - 1)


def _probe(images, points, levels, rows, cache_a, cache_b, tail, guess, order, count, common):
    """Probe tracking (:mod:`granite.optical_flow.probe`): track ``count`` probes first (all
    passes of ``order``, one thread), correct the other tracks' predictions by the homography
    their results give, and return ``(guesses, preset, confirmed)`` for :func:`track_points`
    (the found probes' templates in image B are copied into ``cache_b``); ``confirmed``: the
    probes agreed on a correction (:func:`~granite.optical_flow.probe.prediction_correction`
    found one), so the corrected predictions hold for the frame."""
    idx = probe_indices(guess, count)
    if not len(idx):
        return guess, None, False
    sub_cache = new_template_cache(len(idx), cache_b[1].shape[1], cache_b[1].shape[2])
    new_points, theta, status = track_points(
        *images, points[idx], levels[idx], rows[idx], *cache_a, *sub_cache, *tail,
        guess=guess[idx], order=order, **common)
    found = idx[status]
    for a, sub in zip(cache_b, sub_cache):
        a[found] = sub[status]
    done = np.zeros(len(points), dtype=bool)
    done[found] = True
    done_points = np.zeros_like(points)
    done_points[found] = new_points[status]
    done_theta = np.zeros(len(points))
    done_theta[found] = theta[status]
    H = prediction_correction(points[found] + guess[found], new_points[status])
    guesses = guess if H is None else corrected_guess(points, guess, H)
    return guesses, (done, done_points, done_theta), H is not None


def _global_retry(result, lost, image_a, image_b, images, points, levels, rows, cache_a, cache_b,
                  tail, common) -> None:
    """Track the ``lost`` points of ``result`` (``track_points``'s output, updated in place, and
    their template rows of ``cache_b``) again from where the homography between the two
    8-bit images predicts them (:mod:`granite.optical_flow.global_motion`), guided pass only;
    nothing changes when no homography is found."""
    H = image_homography(image_a, image_b)
    if H is None:
        return
    idx = np.flatnonzero(lost)
    guess = homography_guess(H, points[idx])
    sub_cache = tuple(a[idx] for a in cache_b)
    sub_cache[0][:] = -1  # template rows not computed yet
    new_points, theta, status = track_points(
        *images, points[idx], levels[idx], rows[idx], *cache_a, *sub_cache, *tail,
        guess=guess, order=np.array([PASS_GUESS], dtype=np.int64), **common)
    found = idx[status]
    result[0][found], result[1][found], result[2][found] = new_points[status], theta[status], True
    for a, sub in zip(cache_b, sub_cache):
        a[found] = sub[status]

