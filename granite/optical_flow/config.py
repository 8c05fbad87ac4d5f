"""Configuration of the optical-flow frontend (paper Sec. IV-A).

Defaults are those of the reference monocular configuration (see
``shared/docs/algorithm-notes.md``). All lengths are pixels *of the level they apply to*
unless a field says otherwise.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Any, Mapping

from granite.errors import ConfigError


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
        pattern_scale: scale of the 52-point diamond pattern (2 px lattice spanning ±7 px).
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
            input image (sigma in level-0 pixels) before the pyramid. The default 0.7 makes
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
        local_retry_rounds: not in the reference (0 disables, the reference; default 1). After the
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
    """

    levels: int = 6
    grid_size: int = 40
    detect_all_levels: bool = True
    pattern_scale: float = 0.75
    iterations: int = 6
    fb_threshold_sq: float = 0.03
    fast_threshold: int = 40
    fast_min_threshold: int = 5
    border: int = 19
    margin: float = 2.0
    presmooth_sigma: float = 0.7
    retry_min_flow: float = 2.0
    guess_min_zncc: float = 0.9
    local_retry_rounds: int = 1
    local_retry_neighbours: int = 8
    fb_noise_factor: float = 0.0
    fb_max_sq: float = 0.3

    def __post_init__(self) -> None:
        _check_type(self)
        checks = [
            (1 <= self.levels <= 12, "levels must be in [1, 12]"),
            (self.grid_size >= 4, "grid_size must be >= 4"),
            (0.0 < self.pattern_scale <= 4.0, "pattern_scale must be in (0, 4]"),
            (self.iterations >= 1, "iterations must be >= 1"),
            (self.fb_threshold_sq > 0.0, "fb_threshold_sq must be > 0"),
            (1 <= self.fast_threshold <= 255, "fast_threshold must be in [1, 255]"),
            (
                1 <= self.fast_min_threshold <= self.fast_threshold,
                "fast_min_threshold must be in [1, fast_threshold]",
            ),
            (self.border >= 3, "border must be >= 3 (FAST needs a 3 px ring)"),
            (self.margin >= 2.0, "margin must be >= 2 (gradients read two pixels around a sample)"),
            (0.0 <= self.presmooth_sigma <= 5.0, "presmooth_sigma must be in [0, 5] (0 disables)"),
            (self.retry_min_flow >= 0.0, "retry_min_flow must be >= 0 (0 disables)"),
            (-1.0 <= self.guess_min_zncc <= 1.0, "guess_min_zncc must be in [-1, 1] (-1 disables)"),
            (0 <= self.local_retry_rounds <= 10, "local_retry_rounds must be in [0, 10] (0 disables)"),
            (3 <= self.local_retry_neighbours <= 64, "local_retry_neighbours must be in [3, 64]"),
            (0.0 <= self.fb_noise_factor <= 100.0, "fb_noise_factor must be in [0, 100] (0 disables)"),
            (
                self.fb_noise_factor == 0.0 or self.fb_max_sq >= self.fb_threshold_sq,
                "fb_max_sq must be >= fb_threshold_sq when fb_noise_factor > 0",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"optical flow: {message}")

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


def _check_type(config: OpticalFlowConfig) -> None:
    for f in fields(config):
        value = getattr(config, f.name)
        if f.type in ("int", int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif f.type in ("float", float):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            if ok:
                object.__setattr__(config, f.name, float(value))
        elif f.type in ("bool", bool):
            ok = isinstance(value, bool)
        else:  # pragma: no cover - all fields are covered above
            ok = True
        if not ok:
            raise ConfigError(
                f"optical flow: {f.name} must be of type {f.type}, got {type(value).__name__} {value!r}"
            )
