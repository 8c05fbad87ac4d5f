"""Sliding-window bundle adjustment (paper Sec. IV, Eq. 4-6; IV-B; IV-C Eq. 9).

:class:`SlidingWindow` holds the frame poses ``T_w_c`` of the window (recent frames and
keyframes), the landmarks hosted by its keyframes (bearing + inverse distance, see
:mod:`granite.backend.landmarks`) and their observations, plus the marginalisation prior.
It minimises ``E = E_reproj + E_m (+ E_scalefix + E_nomotion)`` by Gauss-Newton (or
Levenberg-Marquardt) on the decoupled increment of paper Eq. 14, eliminating landmarks with
the Schur complement.

Typical use by the pipeline::

    win = SlidingWindow(camera, BackendConfig())
    win.add_frame(fid, T_w_c_guess, is_keyframe=True)        # first frame: gauge prior
    win.add_landmark(lid, host_fid, bearing_in_host, inv_dist)  # host must be a keyframe
    win.add_observation(lid, fid, uv, level)
    report = win.optimize(snapshot_iteration=4)                # report.snapshot: WindowHessian
    report.snapshot.negative_entropy(fid)                      # keyframe criterion (Eq. 10)
    win.remove_outliers()
    win.marginalize(win.select_frames_to_marginalize())
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterable, Sequence

import numpy as np

from granite.backend.config import BackendConfig
from granite.backend.hessian import WindowHessian, marginalize_dense
from granite.backend.landmarks import LandmarkDatabase, PackedObservations
from granite.backend.priors import MargPrior, ScaleFix
from granite.backend.reprojection import (
    Workspace,
    linearize,
    reprojection_cost,
    reprojection_residuals,
)
from granite.backend.schur import back_substitute, schur_reduce, solve_normal_equations
from granite.geometry import decoupled_increment


@dataclasses.dataclass
class FrameState:
    """A frame of the window: camera pose ``T_w_c`` (4,4) and whether it is a keyframe."""

    T_w_c: np.ndarray
    is_keyframe: bool


@dataclasses.dataclass(frozen=True)
class OptimizeReport:
    """Result of :meth:`SlidingWindow.optimize`.

    ``costs[i]`` is the total cost at the i-th linearisation; ``initial_cost`` the cost before
    the first step, ``final_cost`` after the last. ``snapshot`` is the linearised system at
    iteration ``snapshot_iteration`` (0-based; the last one if the loop stopped earlier).
    ``timings`` holds seconds spent per stage, summed over iterations.
    """

    iterations: int
    initial_cost: float
    final_cost: float
    converged: bool
    costs: tuple[float, ...]
    snapshot: WindowHessian | None
    timings: dict[str, float]
    #: a Gauss-Newton step raised the cost and was undone (Levenberg-Marquardt took over).
    reverted: bool = False


@dataclasses.dataclass(frozen=True)
class MarginalizationReport:
    """Result of :meth:`SlidingWindow.marginalize`: frames removed, of which marginalised
    into the prior (keyframes / prior states), landmarks removed with their hosts, and
    whether the scale-fix term moved into the prior."""

    removed_frames: tuple[int, ...]
    marginalized_frames: tuple[int, ...]
    removed_landmarks: tuple[int, ...]
    scale_fix_marginalized: bool


class _Problem:
    """Packed arrays of one optimisation: pose order, poses, landmark states."""

    def __init__(self, frame_ids: list[int], poses: np.ndarray, poses_lin: np.ndarray,
                 packed: PackedObservations, workspace: Workspace | None = None):
        self.frame_ids = frame_ids
        self.index = {f: i for i, f in enumerate(frame_ids)}
        self.poses = poses
        self.poses_lin = poses_lin
        self.packed = packed
        self.in_prior = np.zeros(len(frame_ids), dtype=bool)
        self.workspace = workspace if workspace is not None else \
            Workspace(packed.num_observations)
        self.pair_keys: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def sync_lin(self) -> None:
        """Pose Jacobians of states not in the prior are evaluated at the current poses."""
        free = ~self.in_prior
        self.poses_lin[free] = self.poses[free]


#: After a Gauss-Newton step raised the cost, this many further :meth:`SlidingWindow.optimize`
#: calls use Levenberg-Marquardt. Measured (about one failed step per sequence): with 0, RMS RPE
#: 0.184 m on assets/sequences/framedrop and 0.042 m on the 640x480 spiral; with 40, 0.118 m
#: and 0.032 m; the other sequences are unchanged.
LM_CALLS_AFTER_FAILED_STEP = 40


class SlidingWindow:
    """Monocular sliding-window estimator over keyframe/frame poses and inverse-distance
    landmarks; see the module docstring for the workflow and ``docs/backend.md``."""

    def __init__(self, camera, config: BackendConfig | None = None):
        self.camera = camera
        self.config = config if config is not None else BackendConfig()
        self._shared_workspace: Workspace | None = None
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget all frames, landmarks and priors (e.g. after a tracking failure)."""
        self._frames: dict[int, FrameState] = {}
        self.landmarks = LandmarkDatabase()
        self.prior = MargPrior.empty()
        self.scale_fix: ScaleFix | None = None
        #: optimisations left that use Levenberg-Marquardt after a Gauss-Newton step failed
        self._lm_calls_left = 0

    @property
    def frame_ids(self) -> list[int]:
        """Ids of the frames in the window, ascending."""
        return sorted(self._frames)

    @property
    def keyframe_ids(self) -> list[int]:
        return [f for f in self.frame_ids if self._frames[f].is_keyframe]

    def __contains__(self, frame_id: int) -> bool:
        return frame_id in self._frames

    def is_keyframe(self, frame_id: int) -> bool:
        return self._frames[frame_id].is_keyframe

    def pose(self, frame_id: int) -> np.ndarray:
        """Current ``T_w_c`` (a copy)."""
        return self._frames[frame_id].T_w_c.copy()

    def poses(self) -> dict[int, np.ndarray]:
        return {f: s.T_w_c.copy() for f, s in self._frames.items()}

    def set_pose(self, frame_id: int, T_w_c: np.ndarray) -> None:
        """Overwrite a pose estimate (e.g. after map initialisation). The linearisation point
        of a state in the prior is unaffected."""
        self._frames[frame_id].T_w_c = _check_pose(T_w_c)

    def add_frame(self, frame_id: int, T_w_c: np.ndarray, is_keyframe: bool = False) -> None:
        """Add a frame state with an initial pose guess. The first frame of an empty window
        gets the gauge prior ``initial_pose_weight * I_6`` (when that weight is > 0)."""
        frame_id = int(frame_id)
        if frame_id in self._frames:
            raise ValueError(f"frame {frame_id} is already in the window")
        T = _check_pose(T_w_c)
        if not self._frames and not self.prior.frame_ids and self.config.initial_pose_weight > 0:
            self.prior = MargPrior.gauge(frame_id, T, self.config.initial_pose_weight)
        self._frames[frame_id] = FrameState(T, bool(is_keyframe))

    def make_keyframe(self, frame_id: int) -> None:
        """Promote a frame of the window to keyframe (paper Sec. IV-D takes the previous
        frame)."""
        self._frames[frame_id].is_keyframe = True

    def add_landmark(self, landmark_id: int, host_frame_id: int, bearing: np.ndarray,
                     inv_dist: float) -> None:
        """Add a landmark hosted by a keyframe: bearing (3,) in the host camera frame and
        inverse distance ``>= 0`` (0 = at infinity), clamped to ``max_inv_dist``."""
        state = self._frames.get(host_frame_id)
        if state is None or not state.is_keyframe:
            raise ValueError(f"landmark {landmark_id}: host {host_frame_id} is not a keyframe "
                             "of the window")
        self.landmarks.add_landmark(int(landmark_id), int(host_frame_id), bearing,
                                    min(float(inv_dist), self.config.max_inv_dist))

    def add_observation(self, landmark_id: int, frame_id: int, uv: np.ndarray,
                        level: int = 0) -> None:
        """Observation of a landmark at pixel ``uv`` in a window frame; ``level`` is the
        pyramid level the feature was created on (weight ``2**-level``)."""
        if frame_id not in self._frames:
            raise KeyError(f"observation in frame {frame_id}, which is not in the window")
        self.landmarks.add_observation(int(landmark_id), frame_id, uv, level)

    def add_observations(self, frame_id: int, landmark_ids: Sequence[int], uvs: np.ndarray,
                         levels: Sequence[int] | None = None, skip_unknown: bool = False) -> int:
        """Several observations made in one frame, in one batch: ``landmark_ids`` (n,),
        ``uvs`` (n, 2), ``levels`` (n,) (default 0). With ``skip_unknown=True`` ids that are
        not landmarks are ignored (e.g. pass all tracks of a frame), otherwise they raise
        ``KeyError``; nothing is added when the batch is invalid. Returns the number added."""
        if frame_id not in self._frames:
            raise KeyError(f"observation in frame {frame_id}, which is not in the window")
        return self.landmarks.add_observations(frame_id, landmark_ids, uvs, levels,
                                               skip_unknown=skip_unknown)

    def remove_landmark(self, landmark_id: int) -> None:
        self.landmarks.remove_landmark(landmark_id)

    def remove_observation(self, landmark_id: int, frame_id: int) -> None:
        self.landmarks.remove_observation(landmark_id, frame_id)

    def set_scale_fix(self, frame_i: int, frame_j: int, length: float,
                      weight: float | None = None) -> None:
        """Scale-fix residual of paper Eq. 9 between two window frames (replaces any previous
        one): ``weight (|t_w_i - t_w_j| - length)^2``, default weight from the config."""
        for f in (frame_i, frame_j):
            if f not in self._frames:
                raise KeyError(f"scale fix: frame {f} is not in the window")
        if frame_i == frame_j or not length > 0:
            raise ValueError("scale fix needs two different frames and a positive length")
        w = self.config.scale_fix_weight if weight is None else float(weight)
        self.scale_fix = ScaleFix(int(frame_i), int(frame_j), float(length), w)

    def clear_scale_fix(self) -> None:
        self.scale_fix = None

    def landmark_in_world(self, landmark_id: int) -> tuple[np.ndarray, float]:
        """``(direction (3,), inv_dist)``: the world point is ``t_w_h + direction / inv_dist``
        (``direction = R_w_h b``, a unit vector); at infinity only the direction is defined."""
        lm = self.landmarks.landmark(landmark_id)
        T = self._frames[lm.host_frame_id].T_w_c
        return T[:3, :3] @ lm.bearing, lm.inv_dist

    def num_connected(self, frame_id: int) -> tuple[int, int]:
        """``(finite, infinite)``: landmarks observed in a frame with ``d > 0`` and ``d = 0``."""
        return self.landmarks.num_connected(frame_id)

    # --------------------------------------------------------------- packing
    def _problem(self, landmark_ids: Iterable[int] | None = None,
                 target_filter: set[int] | None = None) -> _Problem:
        frame_ids = self.frame_ids
        index = {f: i for i, f in enumerate(frame_ids)}
        poses = np.stack([self._frames[f].T_w_c for f in frame_ids]) if frame_ids else \
            np.zeros((0, 4, 4))
        poses_lin = poses.copy()
        for f, T in self.prior.lin_poses.items():
            poses_lin[index[f]] = T
        packed = self.landmarks.pack(index, landmark_ids, target_filter)
        problem = _Problem(frame_ids, poses, poses_lin, packed,
                           self._workspace(packed.num_observations))
        for f in self.prior.lin_poses:
            problem.in_prior[index[f]] = True
        return problem

    def _workspace(self, n: int) -> Workspace:
        """Linearisation buffers for ``n`` observations on the window's shared workspace
        (grown as needed). All problems of the window share this memory: the results of a
        linearisation are valid until the next one (the window never keeps two)."""
        ws = getattr(self, "_shared_workspace", None)
        if ws is None or ws.capacity < n:
            ws = Workspace(max(n, 1024, int(1.25 * (ws.capacity if ws is not None else 0))))
            self._shared_workspace = ws
        return ws.view(n)

    def _no_motion_pairs(self, problem: _Problem) -> list[tuple[int, int]]:
        """Pose-index pairs (h, t), h != t, connected by observations whose landmarks all have
        ``d == 0`` (paper Sec. IV-B), in ascending order of ``h * K + t`` (h < t)."""
        pk = problem.packed
        if (pk.num_observations == 0 or self.config.no_motion_weight <= 0.0
                or not np.any(pk.lm_d == 0.0)):
            return []
        k = len(problem.frame_ids)
        if problem.pair_keys is None:  # observation structure: fixed for the problem
            host = pk.lm_host[pk.obs_lm]
            tgt = pk.obs_tgt
            sel = np.flatnonzero(host != tgt)
            h, t = host[sel], tgt[sel]
            keys = np.minimum(h, t) * k + np.maximum(h, t)
            problem.pair_keys = (keys, pk.obs_lm[sel],
                                 np.bincount(keys, minlength=k * k) > 0)
        keys, obs_lm, linked = problem.pair_keys
        finite = pk.lm_d[obs_lm] > 0.0
        no_motion = linked & ~(np.bincount(keys[finite], minlength=k * k) > 0)
        return [(int(u // k), int(u % k)) for u in np.flatnonzero(no_motion).tolist()]

    def _prior_terms(self, problem: _Problem, pairs: list[tuple[int, int]],
                     include: set[int] | None = None):
        """Dense prior, scale-fix and no-motion terms over the problem's poses. With
        ``include`` only scale-fix and no-motion terms touching those frame ids are added
        (marginalisation); the prior is always added."""
        n6 = 6 * len(problem.frame_ids)
        idx = problem.index
        poses = {f: problem.poses[i] for f, i in idx.items()}
        H_p = np.zeros((n6, n6))
        b_p = np.zeros(n6)
        cost_p = 0.0
        # The current prior always enters (also when marginalising frames it does not touch:
        # the new prior replaces it and must keep its information, e.g. the gauge).
        if self.prior.frame_ids:
            Hm, bm, cost_p = self.prior.linearize(poses)
            rows = np.concatenate([np.arange(6 * idx[f], 6 * idx[f] + 6)
                                   for f in self.prior.frame_ids])
            H_p[np.ix_(rows, rows)] += Hm
            b_p[rows] += bm
        H_s = np.zeros((n6, n6))
        b_s = np.zeros(n6)
        cost_s = 0.0
        sf = self.scale_fix
        if sf is not None and (include is None or include & {sf.frame_i, sf.frame_j}):
            Hs, bs, cost_s = sf.linearize(poses[sf.frame_i], poses[sf.frame_j])
            rows = np.concatenate([np.arange(6 * idx[sf.frame_i], 6 * idx[sf.frame_i] + 6),
                                   np.arange(6 * idx[sf.frame_j], 6 * idx[sf.frame_j] + 6)])
            H_s[np.ix_(rows, rows)] += Hs
            b_s[rows] += bs
        H_n = np.zeros((n6, n6))
        b_n = np.zeros(n6)
        cost_n = 0.0
        fids = problem.frame_ids
        if include is not None:
            pairs = [(h, t) for h, t in pairs if include & {fids[h], fids[t]}]
        if pairs:  # no_motion_terms for every pair, scattered at once
            w = self.config.no_motion_weight
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

    def _prior_cost(self, problem: _Problem, pairs: list[tuple[int, int]]) -> float:
        poses = {f: problem.poses[i] for f, i in problem.index.items()}
        cost = self.prior.linearize(poses)[2] if self.prior.frame_ids else 0.0
        if self.scale_fix is not None:
            sf = self.scale_fix
            cost += sf.linearize(poses[sf.frame_i], poses[sf.frame_j])[2]
        for h, t in pairs:
            d = problem.poses[t][:3, 3] - problem.poses[h][:3, 3]
            cost += self.config.no_motion_weight * float(d @ d)
        return cost

    # ------------------------------------------------------------ linearise
    def _linearize(self, problem: _Problem, lm_lambda: float = 0.0):
        cfg = self.config
        pk = problem.packed
        inv_var = 1.0 / (cfg.obs_std_dev * cfg.obs_std_dev)
        lin = linearize(self.camera, pk, problem.poses, problem.poses_lin, inv_var,
                        cfg.huber_threshold, cfg.infinite_obs_factor, problem.workspace)
        red = schur_reduce(len(problem.frame_ids), pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.r,
                           lin.w, lin.J_h, lin.J_t, lin.J_l, cfg.landmark_damping, lm_lambda)
        return lin, red

    def _system(self, problem: _Problem, lin, red, pairs) -> WindowHessian:
        H_raw, _, H_red, b_red, _, _ = red
        (H_p, b_p, c_p), (H_s, b_s, c_s), (H_n, b_n, c_n) = self._prior_terms(problem, pairs)
        return WindowHessian(
            frame_ids=tuple(problem.frame_ids),
            poses=problem.poses.copy(),
            H=H_red + H_p + H_s + H_n,
            b=b_red + b_p + b_s + b_n,
            H_reprojection=H_red,
            b_reprojection=b_red,
            H_reprojection_raw=H_raw,
            b_reprojection_raw=red[1],
            H_prior=H_p,
            b_prior=b_p,
            H_scale_fix=H_s,
            H_no_motion=H_n,
            cost=lin.cost + c_p + c_s + c_n,
        )

    def hessian_blocks(self) -> WindowHessian:
        """The linearised pose system (landmarks eliminated) at the current estimate."""
        problem = self._problem()
        lin, red = self._linearize(problem)
        return self._system(problem, lin, red, self._no_motion_pairs(problem))

    def pose_information(self, frame_id: int) -> np.ndarray:
        """6x6 marginal information of a pose at the current estimate (Fisher information of
        paper Eq. 10-11: landmarks and all other poses marginalised, priors included)."""
        return self.hessian_blocks().pose_information(frame_id)

    def negative_entropy(self, frame_id: int, include_translation: bool = True) -> float:
        """``ln det`` of the pose's marginal information (paper Eq. 10); see
        :meth:`WindowHessian.negative_entropy`."""
        return self.hessian_blocks().negative_entropy(frame_id, include_translation)

    def cost(self) -> float:
        """Total cost ``E`` at the current estimate."""
        problem = self._problem()
        return self._cost(problem, self._no_motion_pairs(problem))

    def _cost(self, problem: _Problem, pairs) -> float:
        cfg = self.config
        reproj = reprojection_cost(self.camera, problem.packed, problem.poses,
                                   1.0 / cfg.obs_std_dev ** 2, cfg.huber_threshold,
                                   cfg.infinite_obs_factor)
        return reproj + self._prior_cost(problem, pairs)

    # ------------------------------------------------------------- optimise
    def _apply_step(self, problem: _Problem, dx: np.ndarray, dl: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """New poses and landmark states; returns the old ones for restoring."""
        old = (problem.poses.copy(), problem.packed.lm_s.copy(), problem.packed.lm_d.copy())
        for i in range(len(problem.frame_ids)):
            problem.poses[i] = decoupled_increment(problem.poses[i],
                                                   np.ascontiguousarray(dx[6 * i:6 * i + 6]))
        pk = problem.packed
        pk.lm_s += dl[:, :2]
        np.clip(pk.lm_d + dl[:, 2], 0.0, self.config.max_inv_dist, out=pk.lm_d)
        problem.sync_lin()
        return old

    def optimize(self, max_iterations: int | None = None,
                 snapshot_iteration: int | None = None) -> OptimizeReport:
        """Run Gauss-Newton (or LM with ``config.use_lm``) on all window states.

        Each iteration linearises all observations, eliminates landmarks, adds the priors,
        solves the dense pose system, back-substitutes landmarks and updates poses with the
        decoupled increment (paper Eq. 14) and inverse distances with
        ``d <- clip(d, 0, max_inv_dist)`` (paper Sec. IV-B). Stops after ``max_iterations``
        or when the largest pose increment is below ``step_tolerance``. A Gauss-Newton step that
        raises the cost is undone and the remaining iterations are Levenberg-Marquardt steps
        (``report.reverted``).
        """
        cfg = self.config
        iters = cfg.max_iterations if max_iterations is None else int(max_iterations)
        problem = self._problem()
        pk = problem.packed
        timings = {"linearize": 0.0, "priors": 0.0, "solve": 0.0, "update": 0.0}
        costs: list[float] = []
        snapshot = None
        converged = False
        lam = cfg.lm_lambda_init
        done = 0
        undo = None  # state before the last Gauss-Newton step
        reverted = False
        lm_mode = cfg.use_lm or self._lm_calls_left > 0
        self._lm_calls_left = max(self._lm_calls_left - 1, 0)
        if not problem.frame_ids:
            return OptimizeReport(0, 0.0, 0.0, True, (), None, timings)
        for it in range(iters):
            t0 = time.perf_counter()
            lin, red = self._linearize(problem, 0.0)
            t1 = time.perf_counter()
            pairs = self._no_motion_pairs(problem)
            system = self._system(problem, lin, red, pairs)
            t2 = time.perf_counter()
            timings["linearize"] += t1 - t0
            timings["priors"] += t2 - t1
            if not lm_mode and undo is not None and not system.cost <= costs[-1] * (1.0 + 1e-9):
                # The last Gauss-Newton step raised the cost (far from the minimum, or from the
                # first estimates of marginalised states): undo it and go on with damped
                # (Levenberg-Marquardt) steps, which only accept steps that lower the cost.
                problem.poses[:], pk.lm_s[:], pk.lm_d[:] = undo
                problem.sync_lin()
                reverted, lm_mode, undo = True, True, None
                self._lm_calls_left = LM_CALLS_AFTER_FAILED_STEP
                continue
            costs.append(system.cost)
            if snapshot_iteration is not None and it <= snapshot_iteration:
                snapshot = system
            done = it + 1
            if not lm_mode:
                t3 = time.perf_counter()
                dx = solve_normal_equations(system.H, system.b)
                dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h,
                                     lin.J_t, lin.J_l, red[4], red[5])
                t4 = time.perf_counter()
                undo = self._apply_step(problem, dx, dl)
                t5 = time.perf_counter()
                timings["solve"] += t4 - t3
                timings["update"] += t5 - t4
                if not (np.all(np.isfinite(problem.poses)) and np.all(np.isfinite(pk.lm_s))):
                    raise FloatingPointError("bundle adjustment diverged (non-finite state)")
                if np.max(np.abs(dx), initial=0.0) < cfg.step_tolerance:
                    converged = True
                    break
            else:
                status, lam = self._lm_step(problem, lin, red, system, lam, pairs, timings)
                if status != "accepted":
                    converged = status == "converged"
                    break
        final_cost = self._cost(problem, self._no_motion_pairs(problem))
        self._write_back(problem)
        return OptimizeReport(done, costs[0], final_cost, converged, tuple(costs), snapshot,
                              timings, reverted)

    def _lm_step(self, problem: _Problem, lin, red, system: WindowHessian, lam: float,
                 pairs, timings) -> tuple[str, float]:
        """One Levenberg-Marquardt iteration: damp, solve, accept if the cost does not increase,
        otherwise raise lambda and retry. Returns (``"accepted"``, ``"converged"`` (step below
        tolerance) or ``"stalled"`` (lambda at its maximum), new lambda)."""
        cfg = self.config
        pk = problem.packed
        while True:
            t3 = time.perf_counter()
            if lam != 0.0:
                red = schur_reduce(len(problem.frame_ids), pk.lm_ptr, pk.lm_host, pk.obs_tgt,
                                   lin.r, lin.w, lin.J_h, lin.J_t, lin.J_l,
                                   cfg.landmark_damping, lam)
            H = red[2] + system.H - system.H_reprojection
            H = H + lam * np.diag(np.diag(H))
            b = red[3] + system.b - system.b_reprojection
            dx = solve_normal_equations(H, b)
            dl = back_substitute(dx, pk.lm_ptr, pk.lm_host, pk.obs_tgt, lin.w, lin.J_h,
                                 lin.J_t, lin.J_l, red[4], red[5])
            old = self._apply_step(problem, dx, dl)
            new_cost = self._cost(problem, pairs)
            timings["solve"] += time.perf_counter() - t3
            small = np.max(np.abs(dx), initial=0.0) < cfg.step_tolerance
            if np.isfinite(new_cost) and new_cost <= system.cost:
                return ("converged" if small else "accepted"), max(lam / 3.0, cfg.lm_lambda_min)
            problem.poses[:], pk.lm_s[:], pk.lm_d[:] = old
            problem.sync_lin()
            if small:
                return "converged", lam
            if lam >= cfg.lm_lambda_max:
                return "stalled", lam
            lam = min(lam * 10.0, cfg.lm_lambda_max)

    def _write_back(self, problem: _Problem) -> None:
        for i, f in enumerate(problem.frame_ids):
            self._frames[f].T_w_c = problem.poses[i].copy()
        self.landmarks.unpack_states(problem.packed)

    # ------------------------------------------------------------- outliers
    def remove_outliers(self, threshold: float | None = None) -> list[tuple[int, int]]:
        """Remove observations whose reprojection error exceeds ``threshold`` pixels (default
        ``config.outlier_threshold``) or that do not project; landmarks left without any
        observation are removed as well. Returns the removed ``(landmark_id, frame_id)``."""
        thr = self.config.outlier_threshold if threshold is None else float(threshold)
        problem = self._problem()
        pk = problem.packed
        if pk.num_observations == 0:
            return []
        res, valid = reprojection_residuals(self.camera, pk, problem.poses)
        err = np.linalg.norm(res, axis=1)
        bad = np.flatnonzero(~valid | ~(err <= thr))
        removed = []
        for k in bad.tolist():
            lm_id = int(pk.landmark_ids[pk.obs_lm[k]])
            fid = problem.frame_ids[int(pk.obs_tgt[k])]
            self.landmarks.remove_observation(lm_id, fid)
            removed.append((lm_id, fid))
        for lm_id in {lm for lm, _ in removed}:
            if not self.landmarks.observations(lm_id):
                self.landmarks.remove_landmark(lm_id)
        return removed

    # -------------------------------------------------------- marginalise
    def marginalize(self, frame_ids: Iterable[int]) -> MarginalizationReport:
        """Remove frames from the window.

        Keyframes (and any frame that is a state of the prior or of the scale fix) are
        marginalised: together with the landmarks they host, the observations of those
        landmarks in keyframes, the current prior, the scale fix (paper Sec. IV-C) and the
        no-motion terms touching them, they are linearised at the current estimate
        (first-estimate Jacobians for prior states) and eliminated by the Schur complement into
        a new prior ``(H_m, b_m)`` over the remaining connected poses. Observations of
        marginalised landmarks in non-keyframes and observations made in a marginalised
        keyframe of landmarks hosted elsewhere are dropped (as in Basalt). Other frames leave
        by dropping their observations.
        """
        remove = sorted({int(f) for f in frame_ids})
        for f in remove:
            if f not in self._frames:
                raise KeyError(f"marginalize: frame {f} is not in the window")
        if not remove:
            return MarginalizationReport((), (), (), False)
        sf = self.scale_fix
        sf_frames = set() if sf is None else {sf.frame_i, sf.frame_j}
        marg = [f for f in remove
                if self._frames[f].is_keyframe or f in self.prior or f in sf_frames]
        sf_moved = False
        if marg:
            sf_moved = bool(sf_frames & set(marg))
            self._marginalize_states(set(marg), dropped=set(remove) - set(marg))
        removed_lms: list[int] = []
        for f in remove:
            removed_lms.extend(self.landmarks.remove_frame(f))
            del self._frames[f]
        if sf_moved:
            self.scale_fix = None
            if not self._prior_links(sf_frames - set(marg)):
                self._reanchor_scale_fix(sf.weight)
        return MarginalizationReport(tuple(remove), tuple(marg), tuple(sorted(removed_lms)),
                                     sf_moved)

    def _prior_links(self, kept_scale_frames: set[int]) -> bool:
        """Whether the new prior ties the remaining frame of the scale fix to another frame
        (then it carries the scale the fix held)."""
        frames = set(self.prior.frame_ids)
        return bool(frames & kept_scale_frames) and len(frames) > 1

    def _reanchor_scale_fix(self, weight: float) -> None:
        """Not in the reference: the scale fix left with a frame that had no other link, so
        the prior holds no scale; fix the (unobservable) scale again at its current value,
        between the two oldest keyframes whose distance is not negligible."""
        kfs = self.keyframe_ids
        for i, a in enumerate(kfs):
            for b in kfs[i + 1:]:
                length = float(np.linalg.norm(self._frames[a].T_w_c[:3, 3] - self._frames[b].T_w_c[:3, 3]))
                if length > 1e-6:
                    self.scale_fix = ScaleFix(a, b, length, weight)
                    return

    def _marginalize_states(self, marg: set[int], dropped: set[int]) -> None:
        """Replace the prior by the marginal of (prior + factors touching ``marg``) over the
        remaining connected frames; frames in ``dropped`` leave at the same time without
        entering the prior (their no-motion terms are ignored)."""
        keyframes = {f for f in self.frame_ids if self._frames[f].is_keyframe} - dropped
        hosted = sorted(set().union(*(self.landmarks.hosted_by(f) for f in marg)))
        problem = self._problem(hosted, target_filter=keyframes)
        full = self._problem()
        pairs = [(h, t) for h, t in self._no_motion_pairs(full)
                 if not {full.frame_ids[h], full.frame_ids[t]} & dropped]
        lin, red = self._linearize(problem)
        H_red, b_red = red[2], red[3]
        (H_p, b_p, _), (H_s, b_s, _), (H_n, b_n, _) = self._prior_terms(problem, pairs,
                                                                        include=marg)
        H = H_red + H_p + H_s + H_n
        b = b_red + b_p + b_s + b_n
        idx = problem.index
        pk = problem.packed
        touched = set(self.prior.frame_ids)
        touched.update(problem.frame_ids[i] for i in pk.obs_tgt.tolist())
        touched.update(problem.frame_ids[i] for i in pk.lm_host.tolist())
        if self.scale_fix is not None and {self.scale_fix.frame_i,
                                           self.scale_fix.frame_j} & marg:
            touched.update((self.scale_fix.frame_i, self.scale_fix.frame_j))
        for h, t in pairs:
            pair = {problem.frame_ids[h], problem.frame_ids[t]}
            if pair & marg:
                touched.update(pair)
        keep_frames = sorted(touched - marg)
        keep = np.concatenate([np.arange(6 * idx[f], 6 * idx[f] + 6) for f in keep_frames]) \
            if keep_frames else np.zeros(0, dtype=np.int64)
        marg_rows = np.concatenate([np.arange(6 * idx[f], 6 * idx[f] + 6) for f in sorted(marg)])
        H_new, b_new = marginalize_dense(H, b, keep, marg_rows)
        lin_poses = {f: (self.prior.lin_poses[f] if f in self.prior
                         else self._frames[f].T_w_c.copy()) for f in keep_frames}
        new_prior = MargPrior(keep_frames, H_new, b_new, lin_poses)
        # b_new is the gradient at the current estimate; store it relative to the lin points
        new_prior.b = b_new - H_new @ new_prior.delta(
            {f: self._frames[f].T_w_c for f in keep_frames})
        self.prior = new_prior

    def select_frames_to_marginalize(self) -> list[int]:
        """Window policy of the reference (Basalt VO): non-keyframes older than the newest
        ``max_frames`` frames leave; if more than ``max_keyframes`` keyframes remain, one
        keyframe is marginalised: the first (oldest) one with fewer than 5 % of its hosted
        landmarks seen in the newest frame, otherwise the one with the largest DSO distance
        score ``sqrt(|t_k - t_last|) * sum_j 1 / (|t_k - t_j| + 1e-5)`` (the newest
        ``max_frames`` frames are never chosen)."""
        cfg = self.config
        ids = self.frame_ids
        if not ids:
            return []
        recent = set(ids[-cfg.max_frames:])
        out = [f for f in ids if f not in recent and not self._frames[f].is_keyframe]
        kfs = [f for f in self.keyframe_ids if f not in out]
        if len(kfs) <= cfg.max_keyframes:
            return out
        newest = ids[-1]
        seen = self.landmarks.observed_in(newest)
        candidates = [f for f in kfs if f not in recent]
        for f in candidates:
            hosted = self.landmarks.hosted_by(f)
            if not hosted or len(hosted & seen) < 0.05 * len(hosted):
                return out + [f]
        t_last = self._frames[kfs[-1]].T_w_c[:3, 3]
        best, best_score = None, -math.inf
        for f in candidates:
            t_f = self._frames[f].T_w_c[:3, 3]
            denom = sum(1.0 / (np.linalg.norm(t_f - self._frames[g].T_w_c[:3, 3]) + 1e-5)
                        for g in kfs if g != f)
            score = math.sqrt(np.linalg.norm(t_f - t_last)) * denom
            if score > best_score:
                best, best_score = f, score
        return out + ([best] if best is not None else [])


def _check_pose(T: np.ndarray) -> np.ndarray:
    T = np.array(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("pose must be a finite 4x4 matrix T_w_c")
    return T
