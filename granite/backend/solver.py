"""Gauss-Newton / Levenberg-Marquardt on a window problem (paper Sec. IV, Eq. 14).

Each iteration linearises all observations, eliminates landmarks (Schur complement), adds the
priors, solves the dense pose system ``H dx = -b``, back-substitutes landmarks and updates poses
with the decoupled increment and inverse distances with ``d <- clip(d, 0, max_inv_dist)``
(paper Sec. IV-B).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable

import numpy as np

from granite.backend.config import BackendConfig
from granite.backend.hessian import WindowHessian
from granite.backend.linearization import ReducedSystem, WindowCost
from granite.backend.problem import WindowProblem
from granite.backend.reprojection import LinearizedObservations, linearize, reprojection_cost
from granite.backend.schur import back_substitute, solve_normal_equations

#: A Gauss-Newton step "raised the cost" when the new cost exceeds the old one by more than this
#: relative amount: rounding slack of the cost sums, not a tuning setting.
_COST_RISE_TOLERANCE = 1e-9


@dataclasses.dataclass(frozen=True)
class OptimizeReport:
    """Result of :meth:`SlidingWindow.optimize`.

    ``costs[i]`` is the total cost at the i-th linearisation; ``initial_cost`` the cost before
    the first step, ``final_cost`` after the last (evaluated when first read: the VO does not
    need it). ``snapshot`` is the linearised system at
    iteration ``snapshot_iteration`` (0-based; the last one if the loop stopped earlier).
    ``timings`` holds seconds spent per stage, summed over iterations.
    """

    iterations: int
    initial_cost: float
    final_cost_of: Callable[[], float] = dataclasses.field(repr=False, compare=False)
    converged: bool
    costs: tuple[float, ...]
    snapshot: WindowHessian | None
    timings: dict[str, float]
    #: a Gauss-Newton step raised the cost and was undone (Levenberg-Marquardt took over).
    reverted: bool = False
    #: linearisations with landmark elimination (the others of ``iterations`` reused one:
    #: ``config.jacobian_reuse_steps``); 0 where not counted (:func:`optimize_pose`).
    linearizations: int = 0

    @functools.cached_property
    def final_cost(self) -> float:
        return self.final_cost_of()


@dataclasses.dataclass
class SolverState:
    """What the solver remembers between calls: the number of further calls that use
    Levenberg-Marquardt after a Gauss-Newton step failed (``config.lm_calls_after_failed_step``)."""

    lm_calls_left: int = 0


def optimize(problem: WindowProblem, cost: WindowCost, config: BackendConfig,
             state: SolverState, max_iterations: int | None = None,
             snapshot_iteration: int | None = None,
             reuse_linearizations: bool = True) -> OptimizeReport:
    """Optimise the problem's states in place (see the module docstring).

    Plain Gauss-Newton unless ``config.use_lm`` or ``state`` says Levenberg-Marquardt. After
    each linearisation up to ``config.jacobian_reuse_steps`` further Gauss-Newton steps reuse
    its Jacobians, Hessian weights and reduced Hessian with the gradient at the new states
    (:meth:`WindowCost.regradient`), while its Jacobians keep their form (no landmark reached
    or left infinity, no projection became valid or invalid) and the last step lowered the
    cost by what the linearisation predicted (:data:`REUSE_GAIN_TOLERANCE`); a reused step
    that raised the cost is undone and the states linearised again. Stops after
    ``max_iterations`` linearisations (default ``config.max_iterations``; the reused steps do
    not count, ``report.iterations`` counts every step) or when the pose increment is small
    (:func:`step_is_small`). ``reuse_linearizations=False`` linearises at every step whatever
    the setting. ``snapshot`` is the system of the last step whose linearisation
    was at most the ``snapshot_iteration``-th (0-based). A Gauss-Newton step that raises the cost is
    undone and the remaining iterations, and the next ``config.lm_calls_after_failed_step``
    calls, are Levenberg-Marquardt steps (``report.reverted``). Raises ``FloatingPointError``
    when a step makes the state non-finite.
    """
    cfg = config
    iters = cfg.max_iterations if max_iterations is None else int(max_iterations)
    reuse_steps = cfg.jacobian_reuse_steps if reuse_linearizations else 0
    pk = problem.packed
    timings = {"linearize": 0.0, "priors": 0.0, "solve": 0.0, "update": 0.0}
    costs: list[float] = []
    snapshot = None
    converged = False
    lam = cfg.lm_lambda_init
    done = 0
    undo = None  # state before the last Gauss-Newton step
    reverted = False
    lm_mode = cfg.use_lm or state.lm_calls_left > 0
    state.lm_calls_left = max(state.lm_calls_left - 1, 0)
    if not problem.frame_ids:
        return OptimizeReport(0, 0.0, lambda: 0.0, True, (), None, timings)
    # the scene's scale only matters to the relative translation rule (off by default)
    scale = scene_scale(pk.lm_d) if cfg.translation_step_tolerance > 0.0 else None
    base = None  # the last linearisation, and how many more steps may reuse it
    base_at_infinity = None
    reuse_left = 0
    linearizations = 0
    passes = 0
    step_reused = False  # the last step came from a reused linearisation
    predicted = 0.0  # the cost decrease the last step's linearisation predicted
    while True:
        t0 = time.perf_counter()
        priors_before = timings["priors"]
        # reuse the last linearisation while its Jacobians keep their form: no landmark
        # reached or left infinity, no projection became valid or invalid ...
        reuse = (not lm_mode and base is not None and reuse_left > 0
                 and np.array_equal(pk.lm_d == 0.0, base_at_infinity))
        if reuse:
            lin, red = cost.regradient(problem, *base)
            reuse_left -= 1
            reuse = bool(np.array_equal(lin.valid, base[0].valid))
        if reuse:
            t1 = time.perf_counter()
            pairs = cost.no_motion_pairs(problem)
            system = cost.system(problem, lin, red, pairs)
            timings["priors"] += time.perf_counter() - t1
            # ... and the last step lowered the cost as the linearisation predicted (a rise
            # is handled below)
            reuse = (not system.cost <= costs[-1] * (1.0 + _COST_RISE_TOLERANCE)
                     or _model_agrees(costs[-1] - system.cost, predicted))
        if not reuse:
            if linearizations >= iters:
                break
            lin, red = cost.linearize(problem, 0.0)
            base = (lin, red)
            base_at_infinity = pk.lm_d == 0.0
            reuse_left = reuse_steps
            linearizations += 1
            t1 = time.perf_counter()
            pairs = cost.no_motion_pairs(problem)
            system = cost.system(problem, lin, red, pairs)
            timings["priors"] += time.perf_counter() - t1
        passes += 1
        timings["linearize"] += time.perf_counter() - t0 - (timings["priors"] - priors_before)
        if (not lm_mode and undo is not None
                and not system.cost <= costs[-1] * (1.0 + _COST_RISE_TOLERANCE)):
            problem.restore(undo)
            undo = None
            if step_reused:
                # a step of a reused linearisation raised the cost: linearise again there
                reuse_left = 0
                continue
            # The last Gauss-Newton step raised the cost (far from the minimum, or from the
            # first estimates of marginalised states): undo it and go on with damped
            # (Levenberg-Marquardt) steps, which only accept steps that lower the cost.
            reverted, lm_mode = True, True
            state.lm_calls_left = cfg.lm_calls_after_failed_step
            continue
        costs.append(system.cost)
        if snapshot_iteration is not None and linearizations - 1 <= snapshot_iteration:
            snapshot = system
        done = passes
        if not lm_mode:
            t3 = time.perf_counter()
            dx = solve_normal_equations(system.H, system.b)
            if reuse_steps:  # what the gain test of a next reused step compares with
                predicted = predicted_decrease(system.b, dx, red.b_l, red.Hll_inv)
            dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h,
                                 lin.J_l, lin.t_lin, red.Hll_inv, red.b_l)
            t4 = time.perf_counter()
            undo = problem.apply_step(dx, dl, cfg.max_inv_dist)
            step_reused = reuse
            if reuse_steps and not reuse and not step_is_small(dx / REUSE_MAX_STEP, cfg, scale):
                reuse_left = 0  # far from convergence: the next step linearises again
            t5 = time.perf_counter()
            timings["solve"] += t4 - t3
            timings["update"] += t5 - t4
            if not problem.states_finite():
                raise FloatingPointError("bundle adjustment diverged (non-finite state)")
            if step_is_small(dx, cfg, scale):
                converged = True
                break
        else:
            status, lam = _lm_step(problem, cost, cfg, lin, red, system, lam, pairs, timings,
                                   scale)
            if status != "accepted":
                converged = status == "converged"
                break
    # the problem's states are final here and nothing changes them later
    return OptimizeReport(done, costs[0], lambda: cost.cost(problem, cost.no_motion_pairs(problem)),
                          converged, tuple(costs), snapshot,
                          timings, reverted, linearizations)


def optimize_pose(problem: WindowProblem, cost: WindowCost, config: BackendConfig,
                  pose_index: int, max_iterations: int, with_landmarks: bool = False
                  ) -> OptimizeReport:
    """Gauss-Newton on the pose ``pose_index`` (with ``with_landmarks``: and the landmarks of
    ``problem``), every other pose fixed. Without landmarks (motion-only bundle adjustment)
    ``problem`` must hold only observations made in that frame (``target_filter``); with
    them, every observation of its landmarks, which are then eliminated as in
    :func:`optimize` (the pose's block of the Schur-reduced system is the reduced system of
    that pose and the landmarks, the other poses held). The frame must host none of the
    landmarks and be in no prior term: the cost is then the reprojection cost of ``problem``
    alone. Stops after ``max_iterations`` or when the pose increment is small
    (:func:`step_is_small`); a step that raised the cost is undone and ends the loop
    (``report.reverted``). Raises ``FloatingPointError`` when a step makes a state
    non-finite."""
    cfg = config
    pk = problem.packed
    inv_var = 1.0 / (cfg.obs_std_dev * cfg.obs_std_dev)
    robust = (inv_var, cfg.huber_threshold, cfg.infinite_obs_factor)
    rows = slice(6 * pose_index, 6 * pose_index + 6)
    no_landmark_step = np.zeros((pk.num_landmarks, 3))
    timings = {"linearize": 0.0, "priors": 0.0, "solve": 0.0, "update": 0.0}
    costs: list[float] = []
    converged = reverted = False
    done = 0
    for _ in range(int(max_iterations)):
        t0 = time.perf_counter()
        if with_landmarks:
            lin, red = cost.linearize(problem, 0.0)
        else:
            lin = linearize(cost.camera, pk, problem.poses, problem.poses_lin, *robust,
                            problem.workspace)
        t1 = time.perf_counter()
        if costs and not lin.cost <= costs[-1] * (1.0 + _COST_RISE_TOLERANCE):
            problem.restore(undo)
            reverted = True
            break
        costs.append(lin.cost)
        done += 1
        dx = np.zeros(6 * len(problem.frame_ids))
        if with_landmarks:
            dx[rows] = solve_normal_equations(red.H[rows, rows], red.b[rows])
            dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h,
                                 lin.J_l, lin.t_lin, red.Hll_inv, red.b_l)
        else:
            dx[rows] = solve_normal_equations(*target_pose_system(lin, pk.lm_host, pk.obs_lm,
                                                                  pose_index))
            dl = no_landmark_step
        t2 = time.perf_counter()
        undo = problem.apply_step(dx, dl, cfg.max_inv_dist)
        timings["linearize"] += t1 - t0
        timings["solve"] += t2 - t1
        timings["update"] += time.perf_counter() - t2
        if not problem.states_finite():
            raise FloatingPointError("pose refinement diverged (non-finite state)")
        if step_is_small(dx, cfg, None):
            converged = True
            break
    if done and not reverted and not converged:
        # the last step is not checked by a next linearisation: check its cost here
        last = reprojection_cost(cost.camera, pk, problem.poses, *robust)
        if not last <= costs[-1] * (1.0 + _COST_RISE_TOLERANCE):
            problem.restore(undo)
            reverted = True
    return OptimizeReport(done, costs[0] if costs else 0.0,
                          lambda: reprojection_cost(cost.camera, pk, problem.poses, *robust),
                          converged, tuple(costs), None, timings, reverted)


def target_pose_system(lin: LinearizedObservations, lm_host: np.ndarray, obs_lm: np.ndarray,
                       pose_index: int) -> tuple[np.ndarray, np.ndarray]:
    """The 6x6 normal equations ``(H, b)`` (``H dx = -b``) of the observations of ``lin``
    over the twist of their (common) target pose ``pose_index``, hosts and landmarks fixed:
    ``J_t = J_h M`` with ``M = [[-I, [t_h - t_t]x], [0, -I]]``
    (:func:`granite.backend.schur.relative_map`), whose translation columns are ``-J_v`` and
    rotation columns ``J_v [d]x - J_w``, and ``a^T [d]x = a x d`` row by row."""
    J_v, J_w = lin.J_h[:, :, :3], lin.J_h[:, :, 3:]
    d = (lin.t_lin[lm_host[obs_lm]] - lin.t_lin[pose_index])[:, None, :]
    J_t = np.empty(lin.J_h.shape)
    J_t[:, :, :3] = -J_v
    J_t[:, :, 3] = J_v[:, :, 1] * d[:, :, 2] - J_v[:, :, 2] * d[:, :, 1] - J_w[:, :, 0]
    J_t[:, :, 4] = J_v[:, :, 2] * d[:, :, 0] - J_v[:, :, 0] * d[:, :, 2] - J_w[:, :, 1]
    J_t[:, :, 5] = J_v[:, :, 0] * d[:, :, 1] - J_v[:, :, 1] * d[:, :, 0] - J_w[:, :, 2]
    rows = J_t.reshape(-1, 6)
    weights = np.repeat(lin.w, 2)
    weighted = rows.T * weights
    return weighted @ rows, weighted @ lin.r.reshape(-1)


#: A linearisation is reused for the next step only while the cost decrease of the last step
#: is within this fraction of the decrease its quadratic model predicted: there the
#: Jacobians barely change along the step (a gain-ratio test as in trust-region methods).
REUSE_GAIN_TOLERANCE = 0.1
#: ... and only after a step within this factor of the stopping tolerances
#: (:func:`step_is_small` of ``dx / REUSE_MAX_STEP``): near convergence.
REUSE_MAX_STEP = 10.0


def predicted_decrease(b: np.ndarray, dx: np.ndarray, b_l: np.ndarray, Hll_inv: np.ndarray
                       ) -> float:
    """The cost decrease ``-b_full^T [dx, dl]`` that the quadratic model of a linearisation
    predicts for its Gauss-Newton step, from the reduced system's gradient ``b`` (6K,) and pose
    step ``dx``, the landmark gradients ``b_l`` (M,3) and inverse blocks ``Hll_inv`` (M,3,3):
    ``-b^T dx + sum b_l^T H_ll^-1 b_l`` (with ``dl = -H_ll^-1 (b_l + H_lp dx)``; the cost
    ``E = r^T W r`` and ``H dx = -b`` without factors 1/2)."""
    return -float(b @ dx) + float(np.einsum("mi,mij,mj->", b_l, Hll_inv, b_l))


def _model_agrees(actual: float, predicted: float) -> bool:
    """Whether a step's actual cost decrease is within :data:`REUSE_GAIN_TOLERANCE` of the
    decrease ``predicted`` by the linearisation it came from."""
    return predicted > 0.0 and abs(actual - predicted) <= REUSE_GAIN_TOLERANCE * predicted


def scene_scale(inv_dist: np.ndarray) -> float | None:
    """The median distance [map units] of the finite landmarks (inverse distances
    ``inv_dist`` > 0) from their hosts, ``None`` without any."""
    finite = inv_dist[inv_dist > 0.0]
    return float(np.median(1.0 / finite)) if finite.size else None


def step_is_small(dx: np.ndarray, cfg: BackendConfig, scale: float | None) -> bool:
    """Whether the pose increments ``dx`` (6K,: ``[v, w]`` per pose) are below the stopping
    tolerances: every rotation component below ``cfg.step_tolerance`` [rad], every
    translation component below ``cfg.translation_step_tolerance * scale`` (``scale``: the
    scene's median landmark distance, :func:`scene_scale`), or below the absolute
    ``cfg.step_tolerance`` when that is 0 or there is no scale (the reference's rule)."""
    d = dx.reshape(-1, 6)
    if not d.size:
        return True
    if cfg.translation_step_tolerance > 0.0 and scale is not None:
        trans_tol = cfg.translation_step_tolerance * scale
    else:
        trans_tol = cfg.step_tolerance
    return bool(np.max(np.abs(d[:, 3:])) < cfg.step_tolerance
                and np.max(np.abs(d[:, :3])) < trans_tol)


def _lm_step(problem: WindowProblem, cost: WindowCost, cfg: BackendConfig,
             lin: LinearizedObservations, red: ReducedSystem, system: WindowHessian,
             lam: float, pairs, timings, scale: float | None) -> tuple[str, float]:
    """One Levenberg-Marquardt iteration: damp, solve, accept if the cost does not increase,
    otherwise raise lambda and retry. Returns (``"accepted"``, ``"converged"`` (step below
    tolerance) or ``"stalled"`` (lambda at its maximum), new lambda)."""
    pk = problem.packed
    while True:
        t3 = time.perf_counter()
        if lam != 0.0:
            red = cost.reduce(problem, lin, lam)
        H = red.H + system.H - system.H_reprojection
        H = H + lam * np.diag(np.diag(H))
        b = red.b + system.b - system.b_reprojection
        dx = solve_normal_equations(H, b)
        dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h,
                             lin.J_l, lin.t_lin, red.Hll_inv, red.b_l)
        old = problem.apply_step(dx, dl, cfg.max_inv_dist)
        new_cost = cost.cost(problem, pairs)
        timings["solve"] += time.perf_counter() - t3
        small = step_is_small(dx, cfg, scale)
        if np.isfinite(new_cost) and new_cost <= system.cost:
            return ("converged" if small else "accepted"), max(lam / cfg.lm_lambda_decrease,
                                                               cfg.lm_lambda_min)
        problem.restore(old)
        if small:
            return "converged", lam
        if lam >= cfg.lm_lambda_max:
            return "stalled", lam
        lam = min(lam * cfg.lm_lambda_increase, cfg.lm_lambda_max)
