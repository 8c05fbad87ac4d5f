"""Configuration of the optical-flow frontend (paper Sec. IV-A).

Defaults are those of the reference monocular configuration (see
``shared/docs/algorithm-notes.md``). All lengths are pixels *of the level they apply to*
unless a field says otherwise.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Any, Mapping

from granite.config_schema import spec_field, validate_instance
from granite.errors import ConfigError
from granite.optical_flow.patterns import PATTERN_NAMES, pattern_size

#: ``coarse_pattern`` values: ``"same"`` (the ``pattern``) or a pattern name.
COARSE_PATTERN_NAMES = ("same",) + PATTERN_NAMES


@dataclass(frozen=True)
class OpticalFlowConfig:
    """Settings of :class:`granite.optical_flow.FrameToFrameOpticalFlow`.

    Attributes:
        levels: number of pyramid levels (level 0 = full resolution); patches are tracked from
            level ``levels - 1`` down to the level they were created on.
        grid_size: detection cell size in each level's own pixels; at most one new corner per
            cell and none in a cell that already holds a tracked point created at a
            neighbouring level (creation level within ``±1``).
        detect_all_levels: ``True`` detects corners on levels ``0 .. levels-2`` (the paper's
            method); ``False`` detects on level 0 only (the paper's ablation †, Table I).
        pattern: not the reference's (``"pattern52"``, its 52-point diamond on a 2 px lattice
            spanning ±7 px). The default ``"grid11"`` samples an 11 x 11 lattice over the same
            extent: 121 samples instead of 52, so the tracking estimate and the
            forward-backward distance carry less image noise (``docs/optical_flow.md``,
            "Noise"). ``grid9`` and ``grid13`` are the cheaper and the denser choice.
        coarse_pattern: not in the reference (``"same"``: ``pattern`` on every level, as the
            reference). The pattern of the levels above a patch's creation level, which only
            seed the next finer level (their Gauss-Newton stops at 0.1 px): ``"grid7"`` (49
            samples over the same extent) costs 40 % of ``grid11`` per sample pass there, and
            a coarser level's pixels already average 4^k of the input's, so its noise is
            lower. At most as many samples as ``pattern``. The creation level, the
            forward-backward limit and the ZNCC test use ``pattern`` (``docs/optical_flow.md``).
        pattern_scale: scale of the pattern (both kinds span ±7 px before scaling).
        iterations: inverse-compositional Gauss-Newton iterations per pyramid level.
        fb_threshold_sq: forward-backward check; a track is kept when the squared distance
            between its start and the back-tracked start, in pixels of its creation level,
            is below this value.
        fast_threshold: initial FAST threshold (8-bit intensity units).
        fast_min_threshold: the threshold is halved while a cell finds no corner, as long as
            it stays at or above this value.
        border: no corner is detected closer than this to the image border (level pixels).
        margin: a pattern sample (and a patch centre) is inside the image only if at least
            this far from the border (level pixels).
        presmooth_sigma: not in the reference (0 = off, the reference). Gaussian blur of the
            input image (sigma in level-0 pixels) before the pyramid. The default 0.5 makes
            level-0 tracks on noisy and real images survive the forward-backward check far
            more often, at equal or better accuracy (``docs/optical_flow.md``).
        retry_min_flow: not in the reference (set 0 to disable). When the median
            displacement of the points tracked in a frame is at least this long (level-0
            pixels), the points that failed are tracked again starting from that
            displacement instead of zero motion. Helps points whose coarse levels are
            unusable (near the border, small images) follow large motion (frame drops).
        guess_min_zncc: not in the reference; only used for tracks given a predicted position
            (``process(..., predicted=...)``). A track found from its prediction is accepted
            only if, besides the forward-backward check, the zero-mean normalised
            cross-correlation of the patch with its template on the creation level is at
            least this value; otherwise it is tracked as without a prediction. The backward
            pass of a guided track starts near the track's start, so a false match found from
            a wrong prediction can pass the forward-backward check; this rejects them.
            The local-flow retry (below) applies the same test to its matches.
        guided_levels_above: not in the reference (-1: guided tracks go through the whole
            pyramid, as every track does in the reference). A track with a prediction is first
            tracked from it starting this many levels above its creation level only (a
            prediction within a few pixels needs no coarse level, and every level costs as
            much as the finest); if that fails, from the prediction through the whole
            pyramid, then as without a prediction (1: the KLT time per frame drops by 20-45 %
            on the 640x480 bench against -1, ``docs/optical_flow.md``). With 0 (the default)
            a track is kept from its creation level alone only when it ended within half a
            pixel of its prediction and its patch would fit the level above (the
            coarse-to-fine passes require that); otherwise the pass from one level above
            decides (another 30 % of the KLT time on the spiral).
        probe_points: not in the reference (0 disables; the reference has no predictions).
            With predictions, this many tracks (evenly spaced over the tracks with one) are
            tracked first, through all passes; a homography from their predicted to their
            tracked positions (RANSAC 2 px, at least 8 and half of them agreeing) then
            corrects the other tracks' predictions (:mod:`granite.optical_flow.probe`).
        retry_out_of_view: not in the reference (which has no probes). When false (the
            default) and the probes confirmed the predictions (``probe_points``: a correction
            was found), a track the guided passes lost whose corrected prediction lies outside
            the new image (it left the view) is not tracked again from zero motion nor from
            the median flow, which ignore the prediction: on the 640x480 ``aggressive`` flight
            those were 77 % of the retried tracks, the passes found 0.07 of them per frame,
            and they took about half of the retries' time (``docs/optical_flow.md``). Frames
            whose predictions are not confirmed (no probes, no agreement: frame drops, a wrong
            motion model) retry every lost track.
        local_retry_rounds: not in the reference (0 disables: the default and the reference). After the
            other passes, the points still not tracked are tracked again from the median
            displacement of their ``local_retry_neighbours`` nearest tracked points (forward
            from ``p + g``, back from ``p' - g``, forward-backward check and
            ``guess_min_zncc``); repeated this many times, each round using the tracks the
            previous one added. For points whose coarse levels are unusable (near the
            border, small or wide images) under motion that is not a common shift
            (rotation, forward motion), where the global median-flow retry does not help.
        local_retry_neighbours: number of nearest tracked points the local-flow guess is the
            median of.
        fb_noise_factor: not in the reference (0 = the fixed limit ``fb_threshold_sq``, the
            reference). When > 0 the forward-backward limit of each track follows the
            precision its patch can have in the current images: the squared distance must be
            below ``fb_noise_factor**2 * (sigma_A**2 + sigma_B**2) * lambda_max(C) / mean**2``
            (``sigma`` the noise of the creation level in each image, estimated per frame;
            ``C`` the translation block of the template's ``(J^T J)^-1``, ``mean`` the patch
            mean; see :mod:`granite.optical_flow.noise`), clipped to
            ``[fb_threshold_sq, fb_max_sq]``.
        fb_max_sq: upper bound of the noise-scaled limit (creation-level pixels²).
        max_tracks_per_cell: not in the reference (0 = no limit, the reference). After
            tracking, at most this many tracks per detection cell of their creation level are
            kept, the oldest ones (``frame_to_frame.crowded_tracks_kept``).
        global_retry_min_lost: not in the reference (0 = off, the reference). When tracking
            lost at least this share of the points (of at least 20), they are tracked again
            from where one homography between the two images predicts them: ORB matches over
            the whole images and RANSAC (:mod:`granite.optical_flow.global_motion`; frames after
            a burst of dropped frames, whose predictions were far off).
    """

    levels: int = spec_field(6, 1, 12)
    grid_size: int = spec_field(40, 4, 100000)
    detect_all_levels: bool = spec_field(True)
    pattern: str = spec_field("grid11", choices=PATTERN_NAMES, origin="ours", reference="pattern52")
    coarse_pattern: str = spec_field("same", choices=COARSE_PATTERN_NAMES, origin="ours",
                                     doc="\"same\": pattern on every level (the default and the reference)")
    pattern_scale: float = spec_field(0.75, 0.0, 4.0, lo_open=True)
    iterations: int = spec_field(6, 1, 1000)
    fb_threshold_sq: float = spec_field(0.03, 0.0, 1e12, lo_open=True)
    fast_threshold: int = spec_field(40, 1, 255)
    fast_min_threshold: int = spec_field(5, 1, 255, doc="at most fast_threshold")
    border: int = spec_field(19, 3, 100000, doc="FAST needs a 3 px ring")
    margin: float = spec_field(2.0, 2.0, 1e4, doc="gradients read two pixels around a sample")
    presmooth_sigma: float = spec_field(0.5, 0.0, 5.0, origin="ours", reference=0.0,
                                        doc="0 disables (the reference)")
    retry_min_flow: float = spec_field(2.0, 0.0, 1e4, origin="ours", reference=0.0,
                                       doc="0 disables")
    guess_min_zncc: float = spec_field(0.9, -1.0, 1.0, origin="ours", reference=-1.0,
                                       doc="-1 disables; used by guided and local-flow tracking")
    guided_levels_above: int = spec_field(0, -1, 20, origin="ours", reference=-1,
                                          doc="-1: the whole pyramid only (the reference's tracking)")
    probe_points: int = spec_field(32, 0, 10000, origin="ours", reference=0,
                                   doc="0 disables (the reference)")
    retry_out_of_view: bool = spec_field(False, origin="ours", reference=True,
                                         doc="true: tracks predicted outside the image are retried from zero motion "
                                             "and the median flow even when the probes confirmed the predictions")
    local_retry_rounds: int = spec_field(0, 0, 10, origin="ours", doc="0 disables (the default and the reference)")
    local_retry_neighbours: int = spec_field(8, 3, 64, origin="ours")
    fb_noise_factor: float = spec_field(3.0, 0.0, 100.0, origin="ours", reference=0.0,
                                        doc="0 disables (the reference)")
    fb_max_sq: float = spec_field(0.3, 0.0, 1e4, lo_open=True, origin="ours")
    max_tracks_per_cell: int = spec_field(0, 0, 100000, origin="ours", doc="0: no limit (the reference)")
    global_retry_min_lost: float = spec_field(0.7, 0.0, 1.0, origin="ours", reference=0.0,
                                              doc="0 disables (the reference)")

    def __post_init__(self) -> None:
        validate_instance(self, "optical_flow")
        if self.fast_min_threshold > self.fast_threshold:
            raise ConfigError("[optical_flow] fast_min_threshold: must not exceed fast_threshold "
                              f"({self.fast_threshold}), got {self.fast_min_threshold}")
        if self.coarse_pattern != "same" and pattern_size(self.coarse_pattern) > pattern_size(self.pattern):
            raise ConfigError(f"[optical_flow] coarse_pattern: {self.coarse_pattern!r} has more samples "
                              f"than pattern {self.pattern!r}")
        if self.fb_noise_factor > 0.0 and self.fb_max_sq < self.fb_threshold_sq:
            raise ConfigError("[optical_flow] fb_max_sq: must be >= fb_threshold_sq when "
                              f"fb_noise_factor > 0, got {self.fb_max_sq!r}")

    @property
    def detection_levels(self) -> tuple[int, ...]:
        """Pyramid levels on which new corners are detected."""
        if not self.detect_all_levels:
            return (0,)
        return tuple(range(max(1, self.levels - 1)))

    @property
    def fast_thresholds(self) -> tuple[int, ...]:
        """The halving sequence of FAST thresholds tried while a cell finds nothing."""
        out = []
        t = self.fast_threshold
        while t >= self.fast_min_threshold:
            out.append(t)
            t //= 2
        return tuple(out)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "OpticalFlowConfig":
        """Build from a mapping (e.g. a TOML table); unknown keys raise :class:`ConfigError`."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ConfigError(
                f"optical flow: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}"
            )
        return cls(**dict(values))

    def to_dict(self) -> dict[str, Any]:
        """All fields as a plain dict (inverse of :meth:`from_dict`)."""
        return dataclasses.asdict(self)
