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
from granite.backend.reprojection import LinearizedObservations
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
             snapshot_iteration: int | None = None) -> OptimizeReport:
    """Optimise the problem's states in place (see the module docstring).

    Plain Gauss-Newton unless ``config.use_lm`` or ``state`` says Levenberg-Marquardt. Stops
    after ``max_iterations`` (default ``config.max_iterations``) or when the pose increment is
    small (:func:`step_is_small`). A Gauss-Newton step that raises the cost is
    undone and the remaining iterations, and the next ``config.lm_calls_after_failed_step``
    calls, are Levenberg-Marquardt steps (``report.reverted``). Raises ``FloatingPointError``
    when a step makes the state non-finite.
    """
    cfg = config
    iters = cfg.max_iterations if max_iterations is None else int(max_iterations)
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
    for it in range(iters):
        t0 = time.perf_counter()
        lin, red = cost.linearize(problem, 0.0)
        t1 = time.perf_counter()
        pairs = cost.no_motion_pairs(problem)
        system = cost.system(problem, lin, red, pairs)
        t2 = time.perf_counter()
        timings["linearize"] += t1 - t0
        timings["priors"] += t2 - t1
        if (not lm_mode and undo is not None
                and not system.cost <= costs[-1] * (1.0 + _COST_RISE_TOLERANCE)):
            # The last Gauss-Newton step raised the cost (far from the minimum, or from the
            # first estimates of marginalised states): undo it and go on with damped
            # (Levenberg-Marquardt) steps, which only accept steps that lower the cost.
            problem.restore(undo)
            reverted, lm_mode, undo = True, True, None
            state.lm_calls_left = cfg.lm_calls_after_failed_step
            continue
        costs.append(system.cost)
        if snapshot_iteration is not None and it <= snapshot_iteration:
            snapshot = system
        done = it + 1
        if not lm_mode:
            t3 = time.perf_counter()
            dx = solve_normal_equations(system.H, system.b)
            dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h,
                                 lin.J_l, lin.t_lin, red.Hll_inv, red.b_l)
            t4 = time.perf_counter()
            undo = problem.apply_step(dx, dl, cfg.max_inv_dist)
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
                          timings, reverted)


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
