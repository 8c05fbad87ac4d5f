"""Pose priors of the window: marginalisation prior, scale fix (paper Eq. 9) and the
"no motion" prior of points at infinity (paper Sec. IV-B).

All terms contribute to the dense pose system in the convention of :mod:`granite.backend.schur`
(``E = sum r^T W r``, ``H = J^T W J``, ``b = J^T W r``) and use the decoupled twist
``[v, w]`` of paper Eq. 14 on ``T_w_c`` (v in map units, w in radians).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from granite.backend.problem import pose_rows
from granite.geometry import so3_log


def pose_delta(T_w_c: np.ndarray, T_w_c_lin: np.ndarray) -> np.ndarray:
    """Decoupled twist (6,) from ``T_w_c_lin`` to ``T_w_c``: ``[t - t_lin, log(R R_lin^T)]``,
    the inverse of ``granite.geometry.decoupled_increment``."""
    out = np.empty(6)
    out[:3] = T_w_c[:3, 3] - T_w_c_lin[:3, 3]
    out[3:] = so3_log(np.ascontiguousarray(T_w_c[:3, :3] @ T_w_c_lin[:3, :3].T))
    return out


@dataclasses.dataclass
class MargPrior:
    """Gaussian prior ``E_m = dx^T H dx + 2 b^T dx`` (constant dropped) on the poses
    ``frame_ids`` (block ``k`` = rows ``6k:6k+6``), with ``dx`` the decoupled twists from the
    linearisation points ``lin_poses`` (first-estimate Jacobians: the prior is never
    re-linearised, and reprojection Jacobians of these states are evaluated at ``lin_poses``).
    """

    frame_ids: list[int]
    H: np.ndarray
    b: np.ndarray
    lin_poses: dict[int, np.ndarray]

    @classmethod
    def empty(cls) -> MargPrior:
        return cls([], np.zeros((0, 0)), np.zeros(0), {})

    @classmethod
    def gauge(cls, frame_id: int, T_w_c: np.ndarray, weight: float) -> MargPrior:
        """The gauge prior ``weight * I_6`` fixing one pose at ``T_w_c``."""
        return cls([frame_id], weight * np.eye(6), np.zeros(6), {frame_id: T_w_c.copy()})

    def __contains__(self, frame_id: int) -> bool:
        return frame_id in self.lin_poses

    def delta(self, poses: dict[int, np.ndarray]) -> np.ndarray:
        """Stacked twists (6n,) of the current ``poses`` from the linearisation points."""
        return np.concatenate([pose_delta(poses[f], self.lin_poses[f]) for f in self.frame_ids]
                              ) if self.frame_ids else np.zeros(0)

    def linearize(self, poses: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
        """``(H, b + H dx, cost)`` at the current poses, over ``frame_ids``."""
        dx = self.delta(poses)
        return self.H, self.b + self.H @ dx, float(dx @ self.H @ dx + 2.0 * self.b @ dx)


@dataclasses.dataclass(frozen=True)
class ScaleFix:
    """Scale-fix residual of paper Eq. 9: ``w (|t_w_i - t_w_j| - length)^2``.

    ``|trans(T_j^-1 T_i)| = |t_w_i - t_w_j|``, so only the translations enter; with the
    decoupled increment the Jacobian is ``u^T`` on ``v_i`` and ``-u^T`` on ``v_j``, ``u`` the
    unit vector from ``t_w_j`` to ``t_w_i``.
    """

    frame_i: int
    frame_j: int
    length: float
    weight: float

    def linearize(self, T_w_i: np.ndarray, T_w_j: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, float]:
        """``(H (12,12), b (12,), cost)`` over ``[twist_i, twist_j]``."""
        diff = T_w_i[:3, 3] - T_w_j[:3, 3]
        norm = float(np.linalg.norm(diff))
        r = norm - self.length
        J = np.zeros(12)
        if norm > 0.0:
            u = diff / norm
            J[0:3] = u
            J[6:9] = -u
        H = self.weight * np.outer(J, J)
        b = self.weight * J * r
        return H, b, self.weight * r * r


def no_motion_terms(T_w_h: np.ndarray, T_w_t: np.ndarray, weight: float
                    ) -> tuple[np.ndarray, np.ndarray, float]:
    """The prior ``weight |t_w_t - t_w_h|^2`` of paper Sec. IV-B: ``(H (12,12), b (12,), cost)``
    over ``[twist_h, twist_t]``."""
    diff = T_w_t[:3, 3] - T_w_h[:3, 3]
    H = np.zeros((12, 12))
    eye = weight * np.eye(3)
    H[0:3, 0:3] = eye
    H[6:9, 6:9] = eye
    H[0:3, 6:9] = -eye
    H[6:9, 0:3] = -eye
    b = np.zeros(12)
    b[0:3] = -weight * diff
    b[6:9] = weight * diff
    return H, b, float(weight * diff @ diff)


def pose_prior_terms(problem, prior: MargPrior, scale_fix: ScaleFix | None,
                     pairs: list[tuple[int, int]], no_motion_weight: float,
                     include: set[int] | None = None, with_rhs: bool = True):
    """Dense marginalisation-prior, scale-fix and no-motion terms over a
    :class:`~granite.backend.problem.WindowProblem`'s poses: three ``(H, b, cost)`` of size
    6K. ``pairs`` are the problem's no-motion pose-index pairs. With ``include`` only scale-fix
    and no-motion terms touching those frame ids are added (marginalisation); the prior is
    always added (the new prior replaces it and must keep its information, e.g. the gauge).
    ``with_rhs=False``: the prior's gradient and cost are left at 0 (its Hessian does not
    depend on the estimate; the scale fix and no-motion terms are complete either way)."""
    n6 = 6 * len(problem.frame_ids)
    idx = problem.index
    poses = {f: problem.poses[i] for f, i in idx.items()}
    H_p = np.zeros((n6, n6))
    b_p = np.zeros(n6)
    cost_p = 0.0
    if prior.frame_ids:
        if with_rhs:
            Hm, bm, cost_p = prior.linearize(poses)
        else:
            Hm, bm = prior.H, np.zeros(prior.H.shape[0])
        _scatter(H_p, b_p, pose_rows(idx, prior.frame_ids), Hm, bm)
    H_s = np.zeros((n6, n6))
    b_s = np.zeros(n6)
    cost_s = 0.0
    sf = scale_fix
    if sf is not None and (include is None or include & {sf.frame_i, sf.frame_j}):
        Hs, bs, cost_s = sf.linearize(poses[sf.frame_i], poses[sf.frame_j])
        _scatter(H_s, b_s, pose_rows(idx, (sf.frame_i, sf.frame_j)), Hs, bs)
    H_n = np.zeros((n6, n6))
    b_n = np.zeros(n6)
    cost_n = 0.0
    fids = problem.frame_ids
    if include is not None:
        pairs = [(h, t) for h, t in pairs if include & {fids[h], fids[t]}]
    if pairs:  # no_motion_terms for every pair, scattered at once
        w = no_motion_weight
        hs, ts = np.array(pairs, dtype=np.int64).T
        diff = problem.poses[ts, :3, 3] - problem.poses[hs, :3, 3]  # (P, 3)
        k = np.arange(3)
        rh = (6 * hs[:, None] + k).ravel()
        rt = (6 * ts[:, None] + k).ravel()
        ones = np.full(rh.shape, w)
        np.add.at(H_n, (np.concatenate([rh, rt, rh, rt]), np.concatenate([rh, rt, rt, rh])),
                  np.concatenate([ones, ones, -ones, -ones]))
        np.add.at(b_n, rh, -w * diff.ravel())
        np.add.at(b_n, rt, w * diff.ravel())
        cost_n = float(w * np.sum(diff * diff))
    return (H_p, b_p, cost_p), (H_s, b_s, cost_s), (H_n, b_n, cost_n)


def pose_prior_cost(problem, prior: MargPrior, scale_fix: ScaleFix | None,
                    pairs: list[tuple[int, int]], no_motion_weight: float) -> float:
    """The cost of the terms of :func:`pose_prior_terms` at the problem's poses."""
    poses = {f: problem.poses[i] for f, i in problem.index.items()}
    cost = prior.linearize(poses)[2] if prior.frame_ids else 0.0
    if scale_fix is not None:
        sf = scale_fix
        cost += sf.linearize(poses[sf.frame_i], poses[sf.frame_j])[2]
    for h, t in pairs:
        d = problem.poses[t][:3, 3] - problem.poses[h][:3, 3]
        cost += no_motion_weight * float(d @ d)
    return cost


def _scatter(H: np.ndarray, b: np.ndarray, rows: np.ndarray, H_term: np.ndarray,
             b_term: np.ndarray) -> None:
    H[np.ix_(rows, rows)] += H_term
    b[rows] += b_term
