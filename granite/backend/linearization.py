"""The window's cost and its linearisation (paper Eq. 4-7, IV-B, Eq. 9).

``E = E_reproj + E_prior + E_scalefix + E_nomotion`` (no factor 1/2). :class:`WindowCost`
linearises a :class:`~granite.backend.problem.WindowProblem`: all observations (numba kernels),
landmarks eliminated by the Schur complement, plus the pose priors, into the dense pose system
:class:`~granite.backend.hessian.WindowHessian` (``H dx = -b``, pose ``k`` owns rows
``6k:6k+6``, twist ``[v, w]`` of the decoupled increment on ``T_w_c``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from granite.backend.config import BackendConfig
from granite.backend.hessian import WindowHessian
from granite.backend.priors import MargPrior, ScaleFix, pose_prior_cost, pose_prior_terms
from granite.backend.problem import WindowProblem
from granite.backend.reprojection import (LinearizedObservations, linearize, reprojection_cost,
                                          residuals_at)
from granite.backend.schur import reduced_gradient, schur_reduce


class ReducedSystem(NamedTuple):
    """Output of :func:`granite.backend.schur.schur_reduce`: the pose block and gradient before
    landmark elimination, the reduced camera system, the inverted landmark blocks and the
    landmark gradients."""

    H_raw: np.ndarray
    b_raw: np.ndarray
    H: np.ndarray
    b: np.ndarray
    Hll_inv: np.ndarray
    b_l: np.ndarray


class WindowCost:
    """Cost terms of one window state: camera, weights (config), marginalisation prior and
    scale fix. Cheap to build; the window makes one per operation."""

    def __init__(self, camera, config: BackendConfig, prior: MargPrior,
                 scale_fix: ScaleFix | None):
        self.camera = camera
        self.config = config
        self.prior = prior
        self.scale_fix = scale_fix

    def no_motion_pairs(self, problem: WindowProblem) -> list[tuple[int, int]]:
        return problem.no_motion_pairs(self.config.no_motion_weight)

    def linearize(self, problem: WindowProblem, lm_lambda: float = 0.0, with_rhs: bool = True
                  ) -> tuple[LinearizedObservations, ReducedSystem]:
        """Observations linearised at the problem's states (first-estimate Jacobians at
        ``poses_lin``) and the Schur-reduced system with LM damping ``lm_lambda`` on the
        landmark blocks (``with_rhs=False``: the matrices only, see
        :func:`granite.backend.schur.schur_reduce`)."""
        cfg = self.config
        pk = problem.packed
        inv_var = 1.0 / (cfg.obs_std_dev * cfg.obs_std_dev)
        lin = linearize(self.camera, pk, problem.poses, problem.poses_lin, inv_var,
                        cfg.huber_threshold, cfg.infinite_obs_factor, problem.workspace)
        return lin, self.reduce(problem, lin, lm_lambda, with_rhs)

    def reduce(self, problem: WindowProblem, lin: LinearizedObservations,
               lm_lambda: float, with_rhs: bool = True) -> ReducedSystem:
        """Landmark elimination of an existing linearisation (e.g. with another LM damping)."""
        pk = problem.packed
        return ReducedSystem(*schur_reduce(
            len(problem.frame_ids), pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r, lin.w, lin.J_h,
            lin.J_l, lin.t_lin, self.config.landmark_damping, lm_lambda, with_rhs))

    def regradient(self, problem: WindowProblem, lin: LinearizedObservations,
                   red: ReducedSystem) -> tuple[LinearizedObservations, ReducedSystem]:
        """Residuals, cost and gradients at the problem's current states with the Jacobians
        and reduced Hessian of an earlier ``linearize`` of the same problem (a step that
        reuses its linearisation, ``[backend] jacobian_reuse_steps``): the gradient is that
        of the robust cost with the new residuals and weights through the old Jacobians.
        The returned observations carry the new residuals and cost and the old Jacobians
        and Hessian weights ``w`` (what :func:`~granite.backend.schur.back_substitute`
        needs); the returned system the old ``H``, ``H_raw`` and ``Hll_inv``."""
        cfg = self.config
        pk = problem.packed
        r, w, valid, cost = residuals_at(self.camera, pk, problem.poses,
                                         1.0 / (cfg.obs_std_dev * cfg.obs_std_dev),
                                         cfg.huber_threshold, cfg.infinite_obs_factor)
        b_raw, b_red, b_l = reduced_gradient(len(problem.frame_ids), pk.lm_ptr, pk.lm_host,
                                             pk.obs_tgt, r, w, lin.w, lin.J_h, lin.J_l,
                                             lin.t_lin, red.Hll_inv)
        return (LinearizedObservations(r, lin.w, lin.J_h, lin.J_l, lin.t_lin, cost, valid),
                ReducedSystem(red.H_raw, b_raw, red.H, b_red, red.Hll_inv, b_l))

    def prior_terms(self, problem: WindowProblem, pairs: list[tuple[int, int]],
                    include: set[int] | None = None, with_rhs: bool = True):
        """See :func:`granite.backend.priors.pose_prior_terms`."""
        return pose_prior_terms(problem, self.prior, self.scale_fix, pairs,
                                self.config.no_motion_weight, include, with_rhs)

    def system(self, problem: WindowProblem, lin: LinearizedObservations, red: ReducedSystem,
               pairs: list[tuple[int, int]]) -> WindowHessian:
        """The full linearised pose system (landmarks eliminated, priors added)."""
        (H_p, b_p, c_p), (H_s, b_s, c_s), (H_n, b_n, c_n) = self.prior_terms(problem, pairs)
        return WindowHessian(
            frame_ids=tuple(problem.frame_ids),
            poses=problem.poses.copy(),
            H=red.H + H_p + H_s + H_n,
            b=red.b + b_p + b_s + b_n,
            H_reprojection=red.H,
            b_reprojection=red.b,
            H_reprojection_raw=red.H_raw,
            b_reprojection_raw=red.b_raw,
            H_prior=H_p,
            b_prior=b_p,
            H_scale_fix=H_s,
            H_no_motion=H_n,
            cost=lin.cost + c_p + c_s + c_n,
        )

    def cost(self, problem: WindowProblem, pairs: list[tuple[int, int]]) -> float:
        """Total cost ``E`` at the problem's current states."""
        cfg = self.config
        reproj = reprojection_cost(self.camera, problem.packed, problem.poses,
                                   1.0 / cfg.obs_std_dev ** 2, cfg.huber_threshold,
                                   cfg.infinite_obs_factor)
        return reproj + pose_prior_cost(problem, self.prior, self.scale_fix, pairs,
                                        cfg.no_motion_weight)
