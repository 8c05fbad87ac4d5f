"""True relative scale error over time (the "actual relative scale drift" of the paper's Fig. 4).

For every estimate timestamp ``t`` whose pair ``(t - delta, t)`` the RPE evaluates (same
sub-map run, inside the ground truth, first ``delta`` seconds excluded; see
:mod:`granite.evaluation.rpe`)::

    e_t = s_align / s_t - 1,   s_t = |trans(dQ_t)| / |trans(dT_t)|   (Eq. 19)

``s_align`` is the Sim(3) scale that aligns the estimate's sub-map to the ground truth
(:func:`granite.evaluation.ate`), so ``e_t`` is the length of the last ``delta`` seconds of
estimated motion, in the sub-map's aligned scale, relative to the true length, minus one:
0 without drift, +0.1 when the estimate currently moves 10 % too far. Pairs whose true motion
is shorter than ``min_motion`` (ground-truth units) are left out: hovering or turning in place
gives no usable ratio.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from granite.evaluation.ate import ate
from granite.evaluation.rpe import DEFAULT_RPE_DELTA, rpe
from granite.geometry import interpolate_poses
from granite.trajectory import Trajectory


@dataclass(frozen=True, eq=False)
class ScaleErrorSeries:
    """``errors[k]`` (fraction, see module docstring) at ``timestamps[k]`` (seconds)."""

    delta: float
    timestamps: np.ndarray
    errors: np.ndarray

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.errors**2))) if self.errors.size else float("nan")


def relative_scale_error(
    est: Trajectory,
    gt: Trajectory,
    delta: float = DEFAULT_RPE_DELTA,
    align_scales: dict[int, float] | None = None,
    min_motion: float = 0.1,
) -> ScaleErrorSeries:
    """Running relative scale error of ``est`` against ``gt`` over ``delta`` seconds.

    ``align_scales`` maps sub-map index -> Sim(3) alignment scale (default: computed with
    :func:`granite.evaluation.ate`, ``align="sim3"``). Sub-maps without a scale are skipped.
    """
    if align_scales is None:
        align_scales = ate(est, gt, align="sim3").scales
    pairs = rpe(est, gt, delta)
    t = pairs.timestamps
    if t.size == 0:
        return ScaleErrorSeries(float(delta), np.zeros(0), np.zeros(0))
    g0, g1 = gt.timestamps[0], gt.timestamps[-1]
    q_cur = interpolate_poses(gt.timestamps, gt.poses, np.clip(t, g0, g1))
    q_prev = interpolate_poses(gt.timestamps, gt.poses, np.clip(t - delta, g0, g1))
    moved = np.linalg.norm(q_cur[:, :3, 3] - q_prev[:, :3, 3], axis=1) >= min_motion
    rows = np.clip(np.searchsorted(est.timestamps, t), 0, len(est) - 1)
    submaps = est.submap[rows] if est.submap is not None else np.zeros(t.size, dtype=np.int64)
    s_align = np.array([align_scales.get(int(k), np.nan) for k in submaps])
    keep = moved & np.isfinite(s_align)
    errors = s_align[keep] / pairs.scales[keep] - 1.0
    return ScaleErrorSeries(float(delta), t[keep], errors)


@dataclass(frozen=True, eq=False)
class ScaleDriftRate:
    """``rates[k]`` [1/s]: the true scale-drift rate at ``timestamps[k]`` (seconds)."""

    lag: float
    timestamps: np.ndarray
    rates: np.ndarray


def scale_drift_rate(series: ScaleErrorSeries, lag: float = 1.0,
                     submaps: np.ndarray | None = None) -> ScaleDriftRate:
    """True scale-drift rate: the change of the log scale ``l_t = ln(1 + e_t)`` of a
    :class:`ScaleErrorSeries` over ``lag`` seconds, per second,
    ``(l_t - l_{t - lag}) / lag``; the sample nearest to ``t - lag`` (within ``lag / 2``) is
    used, only inside one sub-map (``submaps``: the sub-map of each sample, default one)."""
    t, e = series.timestamps, series.errors
    sub = np.zeros(t.size, dtype=np.int64) if submaps is None else np.asarray(submaps)
    ok = 1.0 + e > 0.0
    t, e, sub = t[ok], e[ok], sub[ok]
    log_scale = np.log1p(e)
    out_t, out_r = [], []
    for k in range(t.size):
        j = int(np.searchsorted(t, t[k] - lag))
        cands = [i for i in (j - 1, j) if 0 <= i < k]
        if not cands:
            continue
        i = min(cands, key=lambda c: abs(t[c] - (t[k] - lag)))
        if abs(t[i] - (t[k] - lag)) > 0.5 * lag or sub[i] != sub[k]:
            continue
        out_t.append(t[k])
        out_r.append((log_scale[k] - log_scale[i]) / (t[k] - t[i]))
    return ScaleDriftRate(float(lag), np.array(out_t), np.array(out_r))
