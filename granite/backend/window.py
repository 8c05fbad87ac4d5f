"""Sliding-window bundle adjustment (paper Sec. IV, Eq. 4-6; IV-B; IV-C Eq. 9).

:class:`SlidingWindow` holds the frame poses ``T_w_c`` of the window (recent frames and
keyframes), the landmarks hosted by its keyframes (bearing + inverse distance, see
:mod:`granite.backend.landmarks`) and their observations, plus the marginalisation prior and
the scale fix. It minimises ``E = E_reproj + E_m (+ E_scalefix + E_nomotion)``
(:mod:`granite.backend.linearization`) by Gauss-Newton or Levenberg-Marquardt
(:mod:`granite.backend.solver`) and marginalises frames into the prior
(:mod:`granite.backend.marginalization`). Which frames leave is the estimator's decision.

Typical use by the pipeline::

    win = SlidingWindow(camera, BackendConfig())
    win.add_frame(fid, T_w_c_guess, is_keyframe=True)        # first frame: gauge prior
    win.add_landmark(lid, host_fid, bearing_in_host, inv_dist)  # host must be a keyframe
    win.add_observation(lid, fid, uv, level)
    report = win.optimize(snapshot_iteration=4)                # report.snapshot: WindowHessian
    report.snapshot.negative_entropy(fid)                      # keyframe criterion (Eq. 10)
    win.remove_outliers()
    win.marginalize(frames_to_marginalize(win, config))        # granite.estimator.window_policy
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence

import numba
import numpy as np

from granite.backend.config import BackendConfig
from granite.backend.hessian import WindowHessian
from granite.backend.landmarks import LandmarkDatabase
from granite.backend.linearization import WindowCost
from granite.backend.marginalization import MarginalizationReport, marginalize_frames
from granite.backend.priors import MargPrior, ScaleFix
from granite.backend.problem import WindowProblem, WorkspacePool
from granite.backend.reprojection import reprojection_residuals
from granite.backend.solver import OptimizeReport, SolverState
from granite.backend.solver import optimize as optimize_problem
from granite.backend.solver import optimize_pose


@dataclasses.dataclass
class FrameState:
    """A frame of the window: camera pose ``T_w_c`` (4,4) and whether it is a keyframe."""

    T_w_c: np.ndarray
    is_keyframe: bool


class SlidingWindow:
    """Monocular sliding-window estimator over keyframe/frame poses and inverse-distance
    landmarks; see the module docstring for the workflow and ``docs/backend.md``."""

    def __init__(self, camera, config: BackendConfig | None = None):
        self.camera = camera
        self.config = config if config is not None else BackendConfig()
        self._workspaces = WorkspacePool()
        self._pose_version = 0  # bumped on every change of frames, poses or the prior
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget all frames, landmarks and priors (e.g. after a tracking failure)."""
        self._frames: dict[int, FrameState] = {}
        self.landmarks = LandmarkDatabase()
        self.prior = MargPrior.empty()
        self.scale_fix: ScaleFix | None = None
        self._solver_state = SolverState()
        #: (the problem of the last :meth:`optimize`, the version it is valid for)
        self._optimized: tuple[WindowProblem, tuple] | None = None

    @property
    def prior(self) -> MargPrior:
        """The marginalisation prior (its linearisation points are the pose Jacobians' points
        of its states)."""
        return self._prior

    @prior.setter
    def prior(self, value: MargPrior) -> None:
        self._prior = value
        self._pose_version += 1

    def _version(self) -> tuple:
        """Changes whenever a frame, pose, the prior, a landmark, an observation or a landmark
        state changes through the window's or its database's methods."""
        return self._pose_version, id(self.landmarks), self.landmarks.version

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
        self._pose_version += 1

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
        self._pose_version += 1

    def make_keyframe(self, frame_id: int) -> None:
        """Promote a frame of the window to keyframe (paper Sec. IV-D takes the previous
        frame)."""
        self._frames[frame_id].is_keyframe = True

    def drop_frame(self, frame_id: int) -> list[int]:
        """Remove a frame without marginalising it: its observations and the landmarks it
        hosts go; returns the ids of the removed landmarks."""
        removed = self.landmarks.remove_frame(frame_id)
        del self._frames[frame_id]
        self._pose_version += 1
        return removed

    # -------------------------------------------------------------- landmarks
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

    def set_inverse_distance(self, landmark_id: int, inv_dist: float) -> None:
        """Overwrite a landmark's inverse distance (``>= 0``, 0 = at infinity), clamped to
        ``max_inv_dist`` (e.g. after the frontend re-triangulated a point at infinity)."""
        self.landmarks.set_inverse_distance(landmark_id,
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

    def landmark_in_world(self, landmark_id: int) -> tuple[np.ndarray, float]:
        """``(direction (3,), inv_dist)``: the world point is ``t_w_h + direction / inv_dist``
        (``direction = R_w_h b``, a unit vector); at infinity only the direction is defined."""
        lm = self.landmarks.landmark(landmark_id)
        T = self._frames[lm.host_frame_id].T_w_c
        return T[:3, :3] @ lm.bearing, lm.inv_dist

    def landmark_points(self, landmark_ids, T_x_w: np.ndarray | None = None) -> np.ndarray:
        """Euclidean points (n, 3) of landmarks with ``d > 0`` in frame x (``T_x_w`` maps world
        into x; the world frame without it), vectorised over the landmarks."""
        s, d, hosts = self.landmarks.states_of(landmark_ids)
        if not len(d):
            return np.zeros((0, 3))
        host_ids, host_of = np.unique(hosts, return_inverse=True)
        T = np.stack([self._frames[int(h)].T_w_c for h in host_ids])
        if T_x_w is not None:
            T = T_x_w @ T
        return _points_from_hosts(s, d, host_of.astype(np.int64), T)

    def num_connected(self, frame_id: int) -> tuple[int, int]:
        """``(finite, infinite)``: landmarks observed in a frame with ``d > 0`` and ``d = 0``."""
        return self.landmarks.num_connected(frame_id)

    # ---------------------------------------------------------------- priors
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

    # --------------------------------------------------------------- problems
    def problem(self, landmark_ids: Iterable[int] | None = None,
                target_filter: set[int] | None = None) -> WindowProblem:
        """The window's states packed for optimisation: all frames, the given landmarks
        (default all) and their observations (only those made in ``target_filter`` frames if
        given). Pose Jacobians of prior states are evaluated at the prior's linearisation
        points (first-estimate Jacobians). Linearisation buffers are shared by all problems
        of the window: results of a linearisation are valid until the next one."""
        frame_ids = self.frame_ids
        index = {f: i for i, f in enumerate(frame_ids)}
        poses = np.stack([self._frames[f].T_w_c for f in frame_ids]) if frame_ids else \
            np.zeros((0, 4, 4))
        poses_lin = poses.copy()
        in_prior = np.zeros(len(frame_ids), dtype=bool)
        for f, T in self.prior.lin_poses.items():
            poses_lin[index[f]] = T
            in_prior[index[f]] = True
        packed = self.landmarks.pack(index, landmark_ids, target_filter)
        return WindowProblem(frame_ids, poses, poses_lin, packed, in_prior,
                             self._workspaces.view(packed.num_observations))

    def write_back(self, problem: WindowProblem) -> None:
        """Copy a problem's poses and landmark states into the window."""
        for i, f in enumerate(problem.frame_ids):
            self._frames[f].T_w_c = problem.poses[i].copy()
        self._pose_version += 1
        self.landmarks.unpack_states(problem.packed)

    def cost_terms(self) -> WindowCost:
        """The cost terms (reprojection, prior, scale fix, no motion) of the current window."""
        return WindowCost(self.camera, self.config, self.prior, self.scale_fix)

    # ------------------------------------------------------------ operations
    def optimize(self, max_iterations: int | None = None,
                 snapshot_iteration: int | None = None,
                 reuse_linearizations: bool = True) -> OptimizeReport:
        """Run Gauss-Newton (or LM with ``config.use_lm``) on all window states; see
        :func:`granite.backend.solver.optimize`. Raises ``FloatingPointError`` (window left
        unchanged) if a step produces a non-finite state."""
        problem = self.problem()
        report = optimize_problem(problem, self.cost_terms(), self.config, self._solver_state,
                                  max_iterations, snapshot_iteration, reuse_linearizations)
        if problem.frame_ids:
            self.write_back(problem)
            self._optimized = (problem, self._version())
        return report

    def _current_problem(self) -> WindowProblem:
        """``problem()``: the last :meth:`optimize`'s own problem while nothing changed since
        (its states are the window's, its structure the same pack), else a new one."""
        if self._optimized is not None and self._optimized[1] == self._version():
            return self._optimized[0]
        return self.problem()

    def pose_refinable_alone(self, frame_id: int) -> bool:
        """Whether :meth:`refine_pose` can optimise the frame's pose alone: it is in the window,
        hosts no landmark, and is in neither the marginalisation prior nor the scale fix."""
        fix = self.scale_fix
        return (frame_id in self._frames and not self.landmarks.hosted_by(frame_id)
                and frame_id not in self.prior.lin_poses
                and (fix is None or frame_id not in (fix.frame_i, fix.frame_j)))

    def refine_pose(self, frame_id: int, max_iterations: int,
                    with_landmarks: bool = False) -> OptimizeReport:
        """Gauss-Newton on one frame's pose alone (motion-only bundle adjustment on its own
        observations) or, ``with_landmarks``, on its pose and the landmarks it observes (on
        all their observations); the other poses fixed, the no-motion prior (weight ``1e-12``
        by default) left out. Needs :meth:`pose_refinable_alone` (``ValueError`` otherwise);
        see :func:`granite.backend.solver.optimize_pose`."""
        if not self.pose_refinable_alone(frame_id):
            raise ValueError(f"frame {frame_id}: its pose cannot be refined alone")
        seen = sorted(self.landmarks.observed_in(frame_id))
        problem = self.problem(seen, None if with_landmarks else {frame_id})
        k = problem.index[frame_id]
        report = optimize_pose(problem, self.cost_terms(), self.config, k, max_iterations,
                               with_landmarks)
        self.write_back(problem)
        return report

    def remove_outliers(self, threshold: float | None = None) -> list[tuple[int, int]]:
        """Remove observations whose reprojection error exceeds ``threshold`` pixels (default
        ``config.outlier_threshold``) or that do not project; landmarks left without any
        observation are removed as well. Returns the removed ``(landmark_id, frame_id)``."""
        thr = self.config.outlier_threshold if threshold is None else float(threshold)
        problem = self._current_problem()
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

    def marginalize(self, frame_ids: Iterable[int]) -> MarginalizationReport:
        """Remove frames from the window, marginalising keyframes and prior / scale-fix states
        into a new prior; see :mod:`granite.backend.marginalization`."""
        return marginalize_frames(self, frame_ids)

    # ------------------------------------------------------- linearised system
    def hessian_blocks(self) -> WindowHessian:
        """The linearised pose system (landmarks eliminated) at the current estimate."""
        problem = self.problem()
        cost = self.cost_terms()
        lin, red = cost.linearize(problem)
        return cost.system(problem, lin, red, cost.no_motion_pairs(problem))

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
        problem = self.problem()
        cost = self.cost_terms()
        return cost.cost(problem, cost.no_motion_pairs(problem))


@numba.njit(cache=True, nogil=True)
def _points_from_hosts(s: np.ndarray, d: np.ndarray, host_of: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``T[host_of[i]] * (bearing(s[i]) / d[i])`` (n, 3): landmark ``i`` (stereographic bearing
    ``s`` (n, 2), inverse distance ``d > 0`` in its host) through its host's pose ``T`` (H, 4, 4)."""
    n = s.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        n2 = s[i, 0] * s[i, 0] + s[i, 1] * s[i, 1]
        k = 1.0 / ((1.0 + n2) * d[i])
        b0, b1, b2 = 2.0 * s[i, 0] * k, 2.0 * s[i, 1] * k, (1.0 - n2) * k
        h = host_of[i]
        for r in range(3):
            out[i, r] = T[h, r, 0] * b0 + T[h, r, 1] * b1 + T[h, r, 2] * b2 + T[h, r, 3]
    return out


def _check_pose(T: np.ndarray) -> np.ndarray:
    T = np.array(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError("pose must be a finite 4x4 matrix T_w_c")
    return T
