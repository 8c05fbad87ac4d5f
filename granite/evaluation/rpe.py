"""Scale-free relative pose error, exactly the paper's Eq. 18-20.

For every estimate timestamp ``t`` with ``t >= t_first + delta`` (``t_first`` = the estimate's
first timestamp; the first ``delta`` seconds are excluded)::

    dT_t = T_{t-delta}^-1 T_t,   dQ_t = Q_{t-delta}^-1 Q_t                      (18)
    s_t  = |trans(dQ_t)| / |trans(dT_t)|                                       (19)
    RMS RPE = sqrt(mean_t |s_t trans(dT_t) - trans(dQ_t)|^2)                   (20)

``T`` are estimated and ``Q`` ground-truth ``T_w_c``. ``T_t`` is the estimate's own pose,
``T_{t-delta}`` is linearly interpolated (translation linear, rotation slerp) from the
estimate, ``Q_t`` and ``Q_{t-delta}`` from the ground truth. Rescaling by ``s_t`` removes the
unknown monocular scale, so only errors of the relative *direction* count; the result is in
ground-truth units.

Choices where the paper is silent (each counted in the result):

* sub-maps: a pair counts only if ``t - delta`` and ``t`` lie in the same sub-map run
  (``t - delta`` not before the first pose of ``t``'s run); otherwise ``skipped_submap``.
* ground truth coverage: ``t`` and ``t - delta`` must lie in the ground truth's time span;
  otherwise ``skipped_no_gt``.
* degenerate pairs: if ``|trans(dT_t)|`` or ``|trans(dQ_t)|`` is at most ``rel_eps`` times the
  spatial extent of its trajectory (the largest distance of a position from the first one,
  per sub-map run for the estimate), ``s_t`` is undefined or meaningless and the pair is
  skipped (``skipped_static``).
* timestamps within 1 us of a boundary (``t_first + delta``, run start, ground-truth span)
  count as on it.

**With a fixed scale** (``fixed_scales``: sub-map index -> scale, e.g. the Sim(3) alignment's
from :func:`granite.evaluation.ate` on the first 100 frames, as the paper's Fig. 4): ``s_t`` of
Eq. 19 is replaced by the pair's sub-map scale, so Eq. 20 also counts errors of the length of
each relative motion, i.e. scale drift, which the per-pair ``s_t`` hides. Static pairs are
kept (there is no ratio to take); pairs of a sub-map without a scale are counted in
``skipped_unaligned``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from granite.evaluation.association import TIME_EPS, check_nonempty, clamp_to_span
from granite.geometry import interpolate_poses
from granite.trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class RpeResult:
    """RMS RPE (``nan`` when no pair is left) and per-pair details.

    Attributes:
        delta: the time offset in seconds.
        rmse: Eq. 20 over the evaluated pairs, in ground-truth units.
        errors: ``(K,)`` ``|s_t trans(dT_t) - trans(dQ_t)|`` per evaluated pair.
        timestamps: ``(K,)`` the ``t`` of each pair.
        scales: ``(K,)`` ``s_t``.
        skipped_static, skipped_submap, skipped_no_gt, skipped_unaligned: pairs left out
            (module docstring).
        fixed_scale: whether ``scales`` are the given per-sub-map scales (not Eq. 19).
    """

    delta: float
    rmse: float
    errors: np.ndarray
    timestamps: np.ndarray
    scales: np.ndarray
    skipped_static: int
    skipped_submap: int
    skipped_no_gt: int
    skipped_unaligned: int = 0
    fixed_scale: bool = False

    @property
    def num_pairs(self) -> int:
        return int(self.errors.shape[0])


def _relative_translations(T_prev: np.ndarray, T_cur: np.ndarray) -> np.ndarray:
    """``trans(T_prev^-1 T_cur) = R_prev^T (p_cur - p_prev)`` for stacks of poses."""
    d = T_cur[:, :3, 3] - T_prev[:, :3, 3]
    return np.einsum("nji,nj->ni", T_prev[:, :3, :3], d)


def _extent(positions: np.ndarray) -> float:
    if len(positions) == 0:
        return 0.0
    return float(np.max(np.linalg.norm(positions - positions[0], axis=1)))


#: The RPE Δ of every command (``granite run``, ``granite demo``, ``granite eval``, the
#: benchmark) unless ``--delta`` says otherwise, in seconds. The paper's 4 s suits MADMAX's 1 Hz
#: ground truth; our test-bench ground truth is 20 Hz, the demo flight lasts 6 s and the benchmark
#: windows 8-15 s, so 1 s gives 20 pairs per second of flight and excludes only the first second,
#: where 4 s would exclude a third of a short flight.
DEFAULT_RPE_DELTA = 1.0


def rpe(est: Trajectory, gt: Trajectory, delta: float = DEFAULT_RPE_DELTA, rel_eps: float = 1e-9,
        fixed_scales: dict[int, float] | None = None) -> RpeResult:
    """RMS RPE of ``est`` against ``gt`` over ``delta`` seconds (paper Eq. 18-20), or with
    the per-sub-map ``fixed_scales`` in place of Eq. 19 (module docstring)."""
    if not (np.isfinite(delta) and delta > 0):
        raise ValueError(f"delta must be a positive number of seconds, got {delta!r}")
    check_nonempty(est, gt)
    ts = est.timestamps
    g0, g1 = gt.timestamps[0], gt.timestamps[-1]
    t_start = ts[0] + delta - TIME_EPS
    cur_idx: list[np.ndarray] = []
    prev_t: list[np.ndarray] = []
    T_prev: list[np.ndarray] = []
    est_eps: list[np.ndarray] = []
    skipped_submap = skipped_no_gt = 0
    for a, b in est.runs():
        idx = np.arange(a, b)[ts[a:b] >= t_start]
        if idx.size == 0:
            continue
        q = ts[idx] - delta
        in_run = q >= ts[a] - TIME_EPS
        skipped_submap += int(np.count_nonzero(~in_run))
        idx, q = idx[in_run], np.maximum(q[in_run], ts[a])
        cur_ok, _ = clamp_to_span(ts[idx], g0, g1)
        prev_ok, _ = clamp_to_span(q, g0, g1)
        ok = cur_ok & prev_ok
        skipped_no_gt += int(np.count_nonzero(~ok))
        idx, q = idx[ok], q[ok]
        if idx.size == 0:
            continue
        cur_idx.append(idx)
        prev_t.append(q)
        T_prev.append(interpolate_poses(ts[a:b], est.poses[a:b], q))
        est_eps.append(np.full(idx.size, rel_eps * _extent(est.positions[a:b])))
    if not cur_idx:
        empty = np.zeros(0)
        return RpeResult(float(delta), float("nan"), empty, empty, empty, 0,
                         skipped_submap, skipped_no_gt, 0, fixed_scales is not None)
    idx = np.concatenate(cur_idx)
    t_cur = ts[idx]
    d_est = _relative_translations(np.concatenate(T_prev), est.poses[idx])
    Q_cur = interpolate_poses(gt.timestamps, gt.poses, np.clip(t_cur, g0, g1))
    Q_prev = interpolate_poses(gt.timestamps, gt.poses, np.clip(np.concatenate(prev_t), g0, g1))
    d_gt = _relative_translations(Q_prev, Q_cur)
    skipped_unaligned = 0
    if fixed_scales is None:
        n_est = np.linalg.norm(d_est, axis=1)
        n_gt = np.linalg.norm(d_gt, axis=1)
        valid = (n_est > np.concatenate(est_eps)) & (n_gt > rel_eps * _extent(gt.positions))
        s = n_gt[valid] / n_est[valid]
        skipped_static = int(np.count_nonzero(~valid))
    else:
        scale_of = np.array([fixed_scales.get(int(k), np.nan) for k in est.submap_ids()[idx]], dtype=np.float64)
        valid = np.isfinite(scale_of)
        s = scale_of[valid]
        skipped_static, skipped_unaligned = 0, int(np.count_nonzero(~valid))
    errors = np.linalg.norm(s[:, None] * d_est[valid] - d_gt[valid], axis=1)
    rmse = float(np.sqrt(np.mean(errors**2))) if errors.size else float("nan")
    return RpeResult(
        delta=float(delta),
        rmse=rmse,
        errors=errors,
        timestamps=t_cur[valid],
        scales=s,
        skipped_static=skipped_static,
        skipped_submap=skipped_submap,
        skipped_no_gt=skipped_no_gt,
        skipped_unaligned=skipped_unaligned,
        fixed_scale=fixed_scales is not None,
    )
