"""Configuration of the sliding-window bundle adjustment (paper Sec. IV, IV-B, IV-C).

Defaults are those of the reference monocular configuration (shared/docs/algorithm-notes.md).
Weights are information values in the units of the cost ``E = sum r^T W r`` with pixel
residuals ``r``; poses are in map units (metres after the scale fix), inverse distances in
1 / map units.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from granite.config_schema import spec_field, validate_instance
from granite.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class BackendConfig:
    """Parameters of :class:`granite.backend.SlidingWindow`.

    Attributes:
        obs_std_dev: pixel noise standard deviation sigma [px]; observation information is
            ``huber_weight * 2**-level / sigma**2`` (paper Eq. 5 and 7).
        huber_threshold: Huber threshold on the residual norm [px].
        infinite_obs_factor: extra information factor of observations of points at infinity
            (inverse distance exactly 0).
        no_motion_weight: weight of the prior ``|t_w_t - t_w_h|^2`` tying the translations of two
            frames connected only by landmarks with d = 0 (paper Sec. IV-B) [1/map unit^2].
            Ours 1e-6 (the reference's form and value give 1e-12 and less): above the round-off
            of the pose system, so that it determines the translations it is meant to
            (docs/backend.md).
        initial_pose_weight: weight of the gauge prior on the first pose of an empty window,
            ``w * I_6`` on the twist ``[v, w]``; 0 disables it.
        scale_fix_weight: default weight of the scale-fix residual of paper Eq. 9.
        max_inv_dist: inverse distances are clamped to ``[0, max_inv_dist]`` after every step.
        max_iterations: Gauss-Newton iterations per :meth:`SlidingWindow.optimize` call.
        step_tolerance: Gauss-Newton stops when every pose increment component is below this
            (the reference stops at 1e-4 too; translations: see ``translation_step_tolerance``).
        translation_step_tolerance: not in the reference (0: off, the default: translations
            against the absolute ``step_tolerance`` in map units, as the reference): the largest
            translation increment must be below this fraction of the median distance of the
            window's finite landmarks from their hosts, so the rule follows the monocular map's
            arbitrary unit (5e-5 equals the reference's 1e-4 at the initialisation's mean
            distance 2.0). On the 60 s spiral (climb to 8 times the start altitude) 5e-5 cuts
            the Gauss-Newton iterations per frame from 5.75 to 4.57 at equal accuracy; the
            aggressive flights' RPE moves within the spread that any change of the stopping
            tolerance gives them (docs/backend.md, "Stopping rule"), so it stays off.
        jacobian_reuse_steps: not in the reference (0: every Gauss-Newton step linearises
            again): in each frame's main optimisation, after a linearisation up to this many
            further steps reuse its Jacobians, Hessian weights and reduced camera system with
            the gradient of the robust cost at the new states (residuals only: a
            frozen-Jacobian step), while the last step lowered the cost as the linearisation
            predicted; ``max_iterations`` counts linearisations. Spiral at 640x480: 2.20 ->
            1.33 linearisations per frame (docs/backend.md, "Reused linearisations").
        outlier_threshold: reprojection error [px] above which an observation is an outlier.
        landmark_damping: added to the diagonal of each landmark's 3x3 block before it is
            eliminated, so that an unobservable inverse distance (no baseline) gives a zero step
            instead of a singular system. It damps the step only, it is not part of the cost.
        use_lm: Levenberg-Marquardt (steps are accepted only when the cost decreases) instead
            of plain Gauss-Newton.
        lm_calls_after_failed_step: not in the reference: after a Gauss-Newton step raised
            the cost (it is undone), this many further optimisations use Levenberg-Marquardt.
            Measured (about one failed step per sequence): with 0, RMS RPE 0.184 m on
            assets/sequences/framedrop and 0.042 m on the 640x480 spiral; with 40, 0.118 m and
            0.032 m; the other sequences are unchanged.
        lm_lambda_init, lm_lambda_min, lm_lambda_max: LM damping, ``H + lambda diag(H)``.
        lm_lambda_decrease, lm_lambda_increase: after an accepted LM step lambda is divided by
            the first (the reference's 3), after a rejected one multiplied by the second.
        max_frames, max_keyframes: window size (3 recent frames + 11 keyframes).
        marg_seen_fraction, marg_distance_epsilon: which keyframe leaves a full window (the
            estimator's policy, :func:`granite.estimator.window_policy.frames_to_marginalize`):
            the oldest one with fewer than this fraction of its hosted landmarks seen in the
            newest frame, else the largest DSO distance score
            ``sqrt(|t_k - t_last|) sum_j 1 / (|t_k - t_j| + marg_distance_epsilon)`` [map units].
            ``marg_seen_fraction`` is ours at 0.3 (the reference and DSO: 0.05): keyframes that
            share little with the current view leave before the window spans the whole flight
            (measured in docs/estimator.md, "Keyframe turnover").
        marg_max_keyframe_age: not in the reference (0: off): the window's time horizon [s].
            The oldest keyframe leaves when it is older than this (relative to the newest
            frame), full window or not, while more than 3 keyframes remain.
        marg_depth_change: not in the reference (0: off): a full window first marginalises
            the keyframe whose median landmark depth differs most from the newest frame's, if
            by more than the factor ``1 + marg_depth_change``.
        reanchor_lost_scale: not in the reference (off): when a marginalisation leaves a
            prior without information on the window's global scale (the keyframes that
            carried it left across a keyframe link with no scale, docs/estimator.md) and no
            scale fix is set, the scale (unobservable then) is fixed again at its current
            value by a scale fix (Eq. 9) between the two oldest keyframes.
    """

    obs_std_dev: float = spec_field(0.5, 0.0, 1e4, lo_open=True)
    huber_threshold: float = spec_field(1.0, 0.0, 1e6, lo_open=True)
    infinite_obs_factor: float = spec_field(0.01, 0.0, 1e6)
    no_motion_weight: float = spec_field(1e-6, 0.0, 1e20, origin="ours", reference=1e-12)
    initial_pose_weight: float = spec_field(1e8, 0.0, 1e20)
    scale_fix_weight: float = spec_field(1e8, 0.0, 1e20)
    max_inv_dist: float = spec_field(5.0, 0.0, 1e6, lo_open=True)
    max_iterations: int = spec_field(7, 1, 1000)
    step_tolerance: float = spec_field(1e-4, 0.0, 1e3)
    translation_step_tolerance: float = spec_field(0.0, 0.0, 1e3, origin="ours", reference=0.0)
    jacobian_reuse_steps: int = spec_field(3, 0, 1000, origin="ours", reference=0)
    outlier_threshold: float = spec_field(3.0, 0.0, 1e6, lo_open=True)
    landmark_damping: float = spec_field(1e-9, 0.0, 1e6, origin="ours",
                                         doc="numerical: damps the step only")
    use_lm: bool = spec_field(False)
    lm_calls_after_failed_step: int = spec_field(40, 0, 1000000, origin="ours")
    lm_lambda_init: float = spec_field(1e-4, 0.0, 1e20, lo_open=True, origin="ours")
    lm_lambda_min: float = spec_field(1e-12, 0.0, 1e20, lo_open=True, origin="ours")
    lm_lambda_max: float = spec_field(1e4, 0.0, 1e20, lo_open=True, origin="ours")
    lm_lambda_decrease: float = spec_field(3.0, 1.0, 1e6, lo_open=True, origin="ours")
    lm_lambda_increase: float = spec_field(10.0, 1.0, 1e6, lo_open=True, origin="ours")
    max_frames: int = spec_field(3, 1, 1000)
    max_keyframes: int = spec_field(11, 2, 1000)
    marg_seen_fraction: float = spec_field(0.3, 0.0, 1.0, origin="ours", reference=0.05)
    marg_distance_epsilon: float = spec_field(1e-5, 0.0, 1e6, lo_open=True)
    marg_max_keyframe_age: float = spec_field(0.0, 0.0, 1e6, origin="ours", reference=0.0)
    marg_depth_change: float = spec_field(0.0, 0.0, 100.0, origin="ours", reference=0.0)
    reanchor_lost_scale: bool = spec_field(False, origin="ours", reference=False)

    def __post_init__(self) -> None:
        validate_instance(self, "backend")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> BackendConfig:
        """Build from a mapping (e.g. a parsed config file section); unknown keys and bad
        values raise :class:`granite.errors.ConfigError`."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"backend: unknown key(s) {', '.join(unknown)}; "
                              f"known: {', '.join(sorted(known))}")
        return cls(**dict(values))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)
