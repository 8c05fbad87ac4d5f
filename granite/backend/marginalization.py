"""Marginalisation of window frames into the prior (paper Sec. IV; FEJ; scale fix of Eq. 9).

Keyframes (and any frame that is a state of the prior or of the scale fix) are marginalised:
together with the landmarks they host, the observations of those landmarks in keyframes, the
current prior, the scale fix (paper Sec. IV-C) and the no-motion terms touching them, they are
linearised at the current estimate (first-estimate Jacobians for prior states) and eliminated by
the Schur complement into a new prior ``(H_m, b_m)`` over the remaining connected poses.
Observations of marginalised landmarks in non-keyframes and observations made in a marginalised
keyframe of landmarks hosted elsewhere are dropped (as in Basalt). Other frames leave by
dropping their observations. Which frames leave is the caller's choice
(:func:`granite.estimator.window_policy.frames_to_marginalize`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from granite.backend.hessian import marginalize_dense
from granite.backend.priors import MargPrior
from granite.backend.problem import pose_rows
from granite.geometry import hat

if TYPE_CHECKING:
    from granite.backend.window import SlidingWindow

#: Two keyframes closer than this [map units] cannot carry a re-anchored scale fix (a guard
#: against a zero-length constraint, whose Jacobian is undefined; not a tuning setting).
_MIN_SCALE_FIX_LENGTH = 1e-6


@dataclasses.dataclass(frozen=True)
class MarginalizationReport:
    """Result of :meth:`SlidingWindow.marginalize`: frames removed, of which marginalised
    into the prior (keyframes / prior states), landmarks removed with their hosts, and
    whether the scale-fix term moved into the prior."""

    removed_frames: tuple[int, ...]
    marginalized_frames: tuple[int, ...]
    removed_landmarks: tuple[int, ...]
    scale_fix_marginalized: bool


def marginalize_frames(window: SlidingWindow, frame_ids: Iterable[int]) -> MarginalizationReport:
    """Remove frames from the window (see the module docstring); the window's prior and scale
    fix are replaced."""
    remove = sorted({int(f) for f in frame_ids})
    for f in remove:
        if f not in window:
            raise KeyError(f"marginalize: frame {f} is not in the window")
    if not remove:
        return MarginalizationReport((), (), (), False)
    sf = window.scale_fix
    sf_frames = set() if sf is None else {sf.frame_i, sf.frame_j}
    marg = [f for f in remove
            if window.is_keyframe(f) or f in window.prior or f in sf_frames]
    sf_moved = False
    if marg:
        sf_moved = bool(sf_frames & set(marg))
        window.prior = _marginalized_prior(window, set(marg), dropped=set(remove) - set(marg))
    removed_lms: list[int] = []
    for f in remove:
        removed_lms.extend(window.drop_frame(f))
    if sf_moved:
        window.clear_scale_fix()
        if not _prior_links(window.prior, sf_frames - set(marg)):
            _reanchor_scale_fix(window, sf.weight)
    elif (marg and window.scale_fix is None and window.config.reanchor_lost_scale
          and prior_scale_information(window.prior) <= UNANCHORED_SCALE_REL):
        _reanchor_scale_fix(window, window.config.scale_fix_weight)
    return MarginalizationReport(tuple(remove), tuple(marg), tuple(sorted(removed_lms)),
                                 sf_moved)


#: A prior whose information on the global scaling of its frames is at most this fraction of
#: its largest diagonal entry (per unit squared length of the scaling) holds no scale: the
#: scale it held left with a keyframe link that carried none. Measured by Λ on a fast flight
#: (docs/estimator.md): 3e-5 of λ_max while the prior held the scale, 2e-14 after.
UNANCHORED_SCALE_REL = 1e-9


def prior_scale_information(prior: MargPrior) -> float:
    """The prior's information along the global scaling of its frames' positions about their
    centre, with the rigid motions of the whole set projected out (their gauge information is
    large), per unit squared length of the scaling, relative to the prior's largest diagonal
    entry. 0 for fewer than two frames or an empty prior. Decoupled increments at the prior's
    linearisation points: a scaling moves ``v_i`` by ``t_i - c``; a rigid motion ``(a, r)``
    by ``v_i = a - [t_i]x r``, ``w_i = r``."""
    n = len(prior.frame_ids)
    H = prior.H
    if n < 2 or not np.any(H):
        return 0.0
    t = np.array([prior.lin_poses[f][:3, 3] for f in prior.frame_ids])
    u = np.zeros((n, 6))
    u[:, :3] = t - t.mean(axis=0)
    u = u.ravel()
    norm_sq = float(u @ u)
    if not norm_sq > 0.0:
        return 0.0
    G = np.zeros((n, 6, 6))
    G[:, :3, :3] = np.eye(3)
    G[:, 3:, 3:] = np.eye(3)
    for k in range(n):
        G[k, :3, 3:] = -hat(t[k])
    G = G.reshape(6 * n, 6)
    HG = H @ G
    a = np.linalg.lstsq(G.T @ HG, -(HG.T @ u), rcond=1e-14)[0]
    x = u + G @ a
    info = float(x @ H @ x)
    return max(info, 0.0) / norm_sq / float(np.max(np.diag(H)))


def _prior_links(prior: MargPrior, kept_scale_frames: set[int]) -> bool:
    """Whether the prior ties the remaining frame of the scale fix to another frame (then it
    carries the scale the fix held)."""
    frames = set(prior.frame_ids)
    return bool(frames & kept_scale_frames) and len(frames) > 1


def _reanchor_scale_fix(window: SlidingWindow, weight: float) -> None:
    """Not in the reference: the scale fix left with a frame that had no other link, so the
    prior holds no scale; fix the (unobservable) scale again at its current value, between the
    two oldest keyframes whose distance is not negligible."""
    kfs = window.keyframe_ids
    for i, a in enumerate(kfs):
        for b in kfs[i + 1:]:
            length = float(np.linalg.norm(window.pose(a)[:3, 3] - window.pose(b)[:3, 3]))
            if length > _MIN_SCALE_FIX_LENGTH:
                window.set_scale_fix(a, b, length, weight)
                return


def _marginalized_prior(window: SlidingWindow, marg: set[int], dropped: set[int]) -> MargPrior:
    """The marginal of (prior + factors touching ``marg``) over the remaining connected frames;
    frames in ``dropped`` leave at the same time without entering the prior (their no-motion
    terms are ignored)."""
    keyframes = set(window.keyframe_ids) - dropped
    db = window.landmarks
    hosted = sorted(set().union(*(db.hosted_by(f) for f in marg)))
    problem = window.problem(hosted, target_filter=keyframes)
    full = window.problem()
    cost = window.cost_terms()
    pairs = [(h, t) for h, t in cost.no_motion_pairs(full)
             if not {full.frame_ids[h], full.frame_ids[t]} & dropped]
    _, red = cost.linearize(problem)
    (H_p, b_p, _), (H_s, b_s, _), (H_n, b_n, _) = cost.prior_terms(problem, pairs, include=marg)
    H = red.H + H_p + H_s + H_n
    b = red.b + b_p + b_s + b_n
    idx = problem.index
    pk = problem.packed
    prior, sf = window.prior, window.scale_fix
    touched = set(prior.frame_ids)
    touched.update(problem.frame_ids[i] for i in pk.obs_tgt.tolist())
    touched.update(problem.frame_ids[i] for i in pk.lm_host.tolist())
    if sf is not None and {sf.frame_i, sf.frame_j} & marg:
        touched.update((sf.frame_i, sf.frame_j))
    for h, t in pairs:
        pair = {problem.frame_ids[h], problem.frame_ids[t]}
        if pair & marg:
            touched.update(pair)
    keep_frames = sorted(touched - marg)
    keep = pose_rows(idx, keep_frames) if keep_frames else np.zeros(0, dtype=np.int64)
    H_new, b_new = marginalize_dense(H, b, keep, pose_rows(idx, sorted(marg)))
    lin_poses = {f: (prior.lin_poses[f] if f in prior else window.pose(f)) for f in keep_frames}
    new_prior = MargPrior(keep_frames, H_new, b_new, lin_poses)
    # b_new is the gradient at the current estimate; store it relative to the lin points
    new_prior.b = b_new - H_new @ new_prior.delta({f: window.pose(f) for f in keep_frames})
    return new_prior
