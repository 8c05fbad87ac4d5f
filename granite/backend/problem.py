"""The packed optimisation problem of a window: pose order, poses, landmark states.

A :class:`WindowProblem` is what the linearisation, the solver and marginalisation work on: the
window's poses ``T_w_c`` stacked in ascending frame-id order (pose ``k`` owns rows ``6k:6k+6``
of every pose system), the linearisation points of the first-estimate Jacobians, and (a subset
of) the landmarks and observations packed into flat arrays
(:class:`~granite.backend.packing.PackedObservations`). States are updated in place; the window
copies them back with :meth:`granite.backend.SlidingWindow.write_back`.
"""

from __future__ import annotations

import numba
import numpy as np

from granite.backend.packing import PackedObservations
from granite.backend.reprojection import Workspace
from granite.geometry import decoupled_increment

#: Saved states of a problem, for undoing a step: (poses, lm_s, lm_d).
StateBackup = tuple[np.ndarray, np.ndarray, np.ndarray]


class WindowProblem:
    """Packed arrays of one optimisation.

    ``frame_ids`` ascending, ``index`` frame id -> pose index, ``poses`` (K,4,4) current
    ``T_w_c``, ``poses_lin`` (K,4,4) the poses the Jacobians are evaluated at (the prior's
    linearisation point for states in the marginalisation prior, ``in_prior``; the current
    pose otherwise), ``packed`` the landmark states and observations, ``workspace`` the
    linearisation buffers.
    """

    def __init__(self, frame_ids: list[int], poses: np.ndarray, poses_lin: np.ndarray,
                 packed: PackedObservations, in_prior: np.ndarray, workspace: Workspace):
        self.frame_ids = frame_ids
        self.index = {f: i for i, f in enumerate(frame_ids)}
        self.poses = poses
        self.poses_lin = poses_lin
        self.packed = packed
        self.in_prior = in_prior
        self.workspace = workspace

    def sync_lin(self) -> None:
        """Pose Jacobians of states not in the prior are evaluated at the current poses."""
        free = ~self.in_prior
        self.poses_lin[free] = self.poses[free]

    def backup(self) -> StateBackup:
        return self.poses.copy(), self.packed.lm_s.copy(), self.packed.lm_d.copy()

    def restore(self, backup: StateBackup) -> None:
        self.poses[:], self.packed.lm_s[:], self.packed.lm_d[:] = backup
        self.sync_lin()

    def apply_step(self, dx: np.ndarray, dl: np.ndarray, max_inv_dist: float) -> StateBackup:
        """Update poses by the decoupled increment (paper Eq. 14) of ``dx`` (6K,) and landmarks
        by ``dl`` (M,3) with ``d <- clip(d + dd, 0, max_inv_dist)``; returns the old states."""
        old = self.backup()
        for i in range(len(self.frame_ids)):
            self.poses[i] = decoupled_increment(self.poses[i],
                                                np.ascontiguousarray(dx[6 * i:6 * i + 6]))
        pk = self.packed
        pk.lm_s += dl[:, :2]
        np.clip(pk.lm_d + dl[:, 2], 0.0, max_inv_dist, out=pk.lm_d)
        self.sync_lin()
        return old

    def states_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.poses)) and np.all(np.isfinite(self.packed.lm_s)))

    def no_motion_pairs(self, weight: float) -> list[tuple[int, int]]:
        """Pose-index pairs (h, t), h != t, connected by observations whose landmarks all have
        ``d == 0`` (paper Sec. IV-B), in ascending order of ``h * K + t`` (h < t); empty when
        the no-motion ``weight`` is 0."""
        pk = self.packed
        if pk.num_observations == 0 or weight <= 0.0 or not np.any(pk.lm_d == 0.0):
            return []
        k = len(self.frame_ids)
        keys = _no_motion_keys(pk.lm_host, pk.lm_d, pk.obs_lm, pk.obs_tgt, k)
        return [(int(u // k), int(u % k)) for u in keys.tolist()]


@numba.njit(cache=True, nogil=True)
def _no_motion_keys(lm_host: np.ndarray, lm_d: np.ndarray, obs_lm: np.ndarray,
                    obs_tgt: np.ndarray, k: int) -> np.ndarray:
    """Ascending keys ``min(h, t) * k + max(h, t)`` of the pose pairs linked by observations
    outside the host, none of them of a landmark with ``d > 0``."""
    linked = np.zeros(k * k, dtype=np.bool_)
    finite = np.zeros(k * k, dtype=np.bool_)
    for o in range(obs_lm.shape[0]):
        i = obs_lm[o]
        h = lm_host[i]
        t = obs_tgt[o]
        if h == t:
            continue
        key = min(h, t) * k + max(h, t)
        linked[key] = True
        if lm_d[i] > 0.0:
            finite[key] = True
    return np.flatnonzero(linked & ~finite)


def pose_rows(index: dict[int, int], frame_ids) -> np.ndarray:
    """Rows (6n,) of the given frames' poses in a pose system ordered by ``index``."""
    return np.concatenate([np.arange(6 * index[f], 6 * index[f] + 6) for f in frame_ids])


class WorkspacePool:
    """One growable set of linearisation buffers shared by all problems of a window: the
    results of a linearisation are valid until the next one (the window never keeps two), and
    the pages stay mapped across calls. Growth policy (at least 1024 observations, +25 %) only
    affects memory and speed, never results."""

    def __init__(self) -> None:
        self._workspace: Workspace | None = None

    def view(self, n: int) -> Workspace:
        """Buffers for ``n`` observations."""
        ws = self._workspace
        if ws is None or ws.capacity < n:
            ws = Workspace(max(n, 1024, int(1.25 * (ws.capacity if ws is not None else 0))))
            self._workspace = ws
        return ws.view(n)
