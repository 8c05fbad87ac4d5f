"""Scale-drift indicator Λ_scaledrift (paper Sec. V, Eq. 11-17): numpy, the chain Jacobian in
numba.

Conventions: poses ``T_w_c`` (camera into world); every pose increment is the decoupled left
increment of paper Eq. 14, twist ``[v, w]`` (translation first): ``R <- exp([w]x) R``,
``t <- t + v``. The keyframes ``k = 0 .. n-1`` (ascending frame id) are re-parametrised as a
kinematic chain: the absolute pose of the oldest keyframe ``T_0`` and the relative poses

    S_k = T_k^-1 T_{k+1}     (maps keyframe k+1 into k; T_{k+1} = T_k S_k; paper Eq. 15's
                              T_{b_{k+1}}^{b_k}, the reference code's ``T_k.inverse() * T_{k+1}``)

each with its own decoupled increment ``eta_k = [nu_k, omega_k]``. To first order (exact
Jacobian, derived in docs/backend.md, "Scale-drift indicator"):

    omega_k = R_k^T (w_{k+1} - w_k),   nu_k = R_k^T (v_{k+1} - v_k) + R_k^T [t_{k+1} - t_k]x w_k

and its inverse, the chain Jacobian ``J = d xi_abs / d [xi_0, eta_0 .. eta_{n-2}]``:

    d xi_j / d xi_0    = [[I, -[t_j - t_0]x], [0, I]]
    d xi_j / d eta_k   = [[R_k, -[t_j - t_{k+1}]x R_k], [0, R_k]]   for k < j, else 0

The information of the chain is ``H_rel = J^T H J``. Then the absolute pose of the oldest
keyframe and every relative rotation are marginalised (Schur complement); what remains is the
relative-translation information ``H_t`` (``3(n-1)`` square) and

    Λ = (sqrt(λ_min(H_t)) * mean_k |trans(S_k)|)^-1                         (paper Eq. 17)
    Λ_ref = (sqrt(λ_min(H_t)) * |sqrt(|q|) ∘ [trans(S_0); ..; trans(S_{n-2})]|)^-1

``Λ_ref`` is the released reference code's variant: ``q`` the unit eigenvector of λ_min, each
relative translation weighted elementwise by the square root of the magnitude of its entries,
then the norm of the whole stacked vector (no mean). A (nearly) repeated λ_min makes ``q``
arbitrary inside its eigenspace; we use the basis-free ``diag(Q Q^T)^(1/4)`` of the eigenspace
``Q`` instead of ``sqrt(|q|)`` (identical for a simple eigenvalue).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numba
import numpy as np

from granite.backend.hessian import information_schur_complement, marginalize_dense
from granite.geometry import hat

if TYPE_CHECKING:
    from granite.backend.linearization import WindowCost
    from granite.backend.problem import WindowProblem, WorkspacePool
    from granite.backend.window import SlidingWindow

#: Fewer keyframes than this: Λ is not defined (paper: a chain of at least two relative poses).
MIN_KEYFRAMES = 3
#: λ_min at or below this fraction of λ_max(H_t): the window has no scale information (no
#: scale anchor: the monocular scale direction is a null direction up to the landmark damping
#: and round-off, measured at about 1e-15..1e-13 of λ_max), Λ is not defined.
ZERO_INFORMATION_REL = 1e-11
#: λ_min below minus this fraction of λ_max: the information is indefinite beyond round-off
#: (a PSD matrix in exact arithmetic), so Λ is not defined. Before ``schur_reduce`` eliminated
#: landmarks by orthogonal projection this happened on the 320x240 spiral's last descent
#: (near-singular landmark blocks); it is now a safeguard (docs/backend.md).
INDEFINITE_REL = 1e-9
#: Eigenvalues within this fraction of λ_max above λ_min span the smallest eigenspace of the
#: reference variant (a round-off bound for the eigenvectors of float64 ``eigh``).
REPEATED_EIGENVALUE_REL = 1e-9


@dataclasses.dataclass(frozen=True)
class KeyframeSystem:
    """The window's information over its keyframes only, at one estimate.

    Keyframe ``frame_ids[k]`` owns rows ``6k:6k+6`` (twist ``[v, w]`` on ``T_w_c``).
    ``H_reprojection``: reprojection terms of observations made in keyframes, landmarks
    eliminated (Schur complement); ``H_priors``: marginalisation prior (+ scale fix when
    included, + no-motion terms) with the non-keyframe states marginalised out of them.
    ``poses`` are the current estimates, ``poses_lin`` the points the Jacobians were evaluated
    at (first-estimate points for prior states, the current estimate for the others).
    """

    frame_ids: tuple[int, ...]
    poses: np.ndarray
    poses_lin: np.ndarray
    H_reprojection: np.ndarray
    H_priors: np.ndarray
    scale_fix_included: bool

    @property
    def H(self) -> np.ndarray:
        return self.H_reprojection + self.H_priors


@dataclasses.dataclass(frozen=True)
class ScaleDriftResult:
    """Λ (Eq. 17) and the reference variant, ``None`` where not defined (``reason`` says why).
    ``lambda_min``/``lambda_max`` of ``H_t`` [1/map unit^2], ``mean_translation`` [map units]."""

    value: float | None
    value_ref: float | None
    num_keyframes: int
    lambda_min: float | None = None
    lambda_max: float | None = None
    mean_translation: float | None = None
    reason: str = ""

    @property
    def defined(self) -> bool:
        return self.value is not None


def relative_poses(poses: np.ndarray) -> np.ndarray:
    """``S_k = T_k^-1 T_{k+1}`` (n-1, 4, 4) of absolute poses ``T_w_c`` (n, 4, 4)."""
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    Rt = R[:-1].transpose(0, 2, 1)
    S = np.tile(np.eye(4), (len(poses) - 1, 1, 1))
    S[:, :3, :3] = Rt @ R[1:]
    S[:, :3, 3] = (Rt @ (t[1:] - t[:-1])[:, :, None])[:, :, 0]
    return S


@numba.njit(cache=True, nogil=True)
def chain_jacobian(poses: np.ndarray) -> np.ndarray:
    """``J = d xi_abs / d [xi_0, eta_0, .., eta_{n-2}]`` (6n, 6n) at absolute poses (n, 4, 4):
    block row ``j`` is keyframe ``j``'s decoupled twist, block column 0 the oldest keyframe's
    twist, column ``k+1`` the decoupled twist of ``S_k`` (see the module docstring)."""
    n = poses.shape[0]
    J = np.zeros((6 * n, 6 * n))
    d = np.empty(3)
    for j in range(n):
        r = 6 * j
        for a in range(6):
            J[r + a, a] = 1.0
        for a in range(3):
            d[a] = poses[j, a, 3] - poses[0, a, 3]
        # -[d]x into the rows of v_j, columns of w_0
        J[r, 4], J[r, 5] = d[2], -d[1]
        J[r + 1, 3], J[r + 1, 5] = -d[2], d[0]
        J[r + 2, 3], J[r + 2, 4] = d[1], -d[0]
        for k in range(j):
            c = 6 * (k + 1)
            for a in range(3):
                d[a] = poses[j, a, 3] - poses[k + 1, a, 3]
            for a in range(3):
                for b in range(3):
                    R_ab = poses[k, a, b]
                    J[r + a, c + b] = R_ab
                    J[r + 3 + a, c + 3 + b] = R_ab
            # -[d]x R_k: row a of [d]x is (d x e_a)^T, i.e. [d]x R = d x (columns of R)
            for b in range(3):
                x, y, z = poses[k, 0, b], poses[k, 1, b], poses[k, 2, b]
                J[r, c + 3 + b] = -(d[1] * z - d[2] * y)
                J[r + 1, c + 3 + b] = -(d[2] * x - d[0] * z)
                J[r + 2, c + 3 + b] = -(d[0] * y - d[1] * x)
    return J


def chain_jacobian_inverse(poses: np.ndarray) -> np.ndarray:
    """``d [xi_0, eta_0, .., eta_{n-2}] / d xi_abs`` (6n, 6n): the inverse of
    :func:`chain_jacobian`, from the first-order expansion of ``S_k = T_k^-1 T_{k+1}``."""
    n = len(poses)
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    A = np.zeros((6 * n, 6 * n))
    A[0:6, 0:6] = np.eye(6)
    for k in range(n - 1):
        r, a, b = 6 * (k + 1), 6 * k, 6 * (k + 1)
        Rt = R[k].T
        A[r:r + 3, a:a + 3] = -Rt
        A[r:r + 3, b:b + 3] = Rt
        A[r:r + 3, a + 3:a + 6] = Rt @ hat(t[k + 1] - t[k])
        A[r + 3:r + 6, a + 3:a + 6] = -Rt
        A[r + 3:r + 6, b + 3:b + 6] = Rt
    return A


#: The Cholesky path of :func:`_chain_translation_information` needs every squared pivot of the
#: Jacobi-scaled block to marginalise above this (as ``hessian.information_schur_complement``).
_CHOLESKY_MIN_PIVOT2 = 1e-12


@numba.njit(cache=True, nogil=True)
def _chain_translation_information(H: np.ndarray, poses: np.ndarray) -> tuple[bool, np.ndarray]:
    """:func:`relative_translation_information` in one GIL-free kernel: ``J^T H J``
    symmetrised, then the Schur complement by a Jacobi-scaled Cholesky factorisation of the
    block to marginalise (the oldest pose, then each relative rotation; the kept relative
    translations in chain order). Returns ``(ok, H_t)``; ``ok`` is False when that block is
    not safely positive definite (a squared pivot at most :data:`_CHOLESKY_MIN_PIVOT2`, a
    non-positive diagonal), and the caller takes the generalised inverse instead."""
    n = poses.shape[0]
    J = chain_jacobian(poses)
    Hr = np.ascontiguousarray(J.T) @ (np.ascontiguousarray(H) @ J)
    N = 6 * n
    m = 6 + 3 * (n - 1)
    k = N - m
    order = np.empty(N, dtype=np.int64)
    for a in range(6):
        order[a] = a
    for j in range(1, n):
        for a in range(3):
            order[6 + 3 * (j - 1) + a] = 6 * j + 3 + a  # rotations: marginalised
            order[m + 3 * (j - 1) + a] = 6 * j + a  # translations: kept
    P = np.empty((N, N))
    for a in range(N):
        for b in range(N):
            P[a, b] = 0.5 * (Hr[order[a], order[b]] + Hr[order[b], order[a]])
    sc = np.empty(m)
    for a in range(m):
        if not P[a, a] > 0.0:
            return False, np.zeros((k, k))
        sc[a] = 1.0 / np.sqrt(P[a, a])
    L = np.zeros((m, m))
    for j in range(m):
        s = P[j, j] * sc[j] * sc[j]
        for c in range(j):
            s -= L[j, c] * L[j, c]
        if not s > _CHOLESKY_MIN_PIVOT2:
            return False, np.zeros((k, k))
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, m):
            t = P[i, j] * sc[i] * sc[j]
            for c in range(j):
                t -= L[i, c] * L[j, c]
            L[i, j] = t / L[j, j]
    X = np.empty((m, k))  # L^-1 (diag(sc) P_mk)
    for col in range(k):
        for i in range(m):
            t = sc[i] * P[i, m + col]
            for c in range(i):
                t -= L[i, c] * X[c, col]
            X[i, col] = t / L[i, i]
    out = np.empty((k, k))
    for a in range(k):
        for b in range(a, k):
            t = 0.0
            for i in range(m):
                t += X[i, a] * X[i, b]
            out[a, b] = P[m + a, m + b] - t
    for a in range(k):
        for b in range(a):
            out[a, b] = out[b, a]
    return True, out


def relative_translation_information(H: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``H_t`` (3(n-1) square): the absolute information ``H`` (6n square, decoupled twists at
    ``poses``) moved onto the chain (``J^T H J``), then the oldest keyframe's absolute pose and
    every relative rotation marginalised (Schur complement; a GIL-free Cholesky kernel, the
    generalised inverse for unconstrained or nearly unconstrained directions)."""
    ok, H_t = _chain_translation_information(np.asarray(H, dtype=np.float64),
                                             np.ascontiguousarray(poses, dtype=np.float64))
    if ok:
        return H_t
    J = chain_jacobian(poses)
    H_rel = J.T @ H @ J
    n = len(poses)
    is_keep = np.zeros((n, 6), dtype=bool)
    is_keep[1:, :3] = True  # relative translations; the oldest pose and all rotations go
    keep = np.flatnonzero(is_keep.ravel())
    marg = np.flatnonzero(~is_keep.ravel())
    return information_schur_complement(0.5 * (H_rel + H_rel.T), keep, marg)


def indicator_from_information(H_t: np.ndarray, translations: np.ndarray,
                               translations_lin: np.ndarray | None = None
                               ) -> tuple[float | None, float | None, float, float, str]:
    """``(Λ, Λ_ref, λ_min, λ_max, reason)`` from the relative-translation information ``H_t``
    and the relative translations (n-1, 3) (see the module docstring); ``None`` values where
    not defined, with the reason. ``translations_lin``: the relative translations at the
    points ``H_t`` was linearised at (default ``translations``), whose scaling is the
    window's scale direction (it tells a missing anchor from an unlinked keyframe)."""
    translations = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    if not (np.all(np.isfinite(H_t)) and np.all(np.isfinite(translations))):
        return None, None, math.nan, math.nan, "non-finite information or poses"
    vals, vecs = np.linalg.eigh(0.5 * (H_t + H_t.T))
    lam_min, lam_max = float(vals[0]), float(vals[-1])
    if not lam_max > 0.0:
        return None, None, lam_min, lam_max, "no translation information"
    if lam_min < -INDEFINITE_REL * lam_max:
        return None, None, lam_min, lam_max, "indefinite information (round-off)"
    if not lam_min > ZERO_INFORMATION_REL * lam_max:
        return None, None, lam_min, lam_max, _no_scale_reason(
            H_t, lam_max, translations if translations_lin is None else translations_lin)
    mean_t = float(np.mean(np.linalg.norm(translations, axis=1)))
    if not mean_t > 0.0:
        return None, None, lam_min, lam_max, "keyframes at one position"
    value = 1.0 / (math.sqrt(lam_min) * mean_t)
    cluster = vals <= lam_min + REPEATED_EIGENVALUE_REL * lam_max
    Q = vecs[:, cluster]
    weights = np.sum(Q * Q, axis=1) ** 0.25
    weighted = float(np.linalg.norm(weights * translations.ravel()))
    value_ref = 1.0 / (math.sqrt(lam_min) * weighted) if weighted > 0.0 else None
    value = value if math.isfinite(value) else None
    value_ref = value_ref if value_ref is not None and math.isfinite(value_ref) else None
    return value, value_ref, lam_min, lam_max, "" if value is not None else "not finite"


#: The scaling of the whole chain (all relative translations, unit norm) has at most this
#: fraction of λ_max(H_t) as information: nothing anchors the window's scale. Measured on a
#: fast 320x240 flight: 2.6e-5 .. 4.6e-5 while the prior held the scale, 2e-14 .. 2e-13
#: after it lost it; 1e-14 on a synthetic window with the gauge prior only.
UNANCHORED_REL = 1e-9
NO_SCALE_ANCHOR = "no scale information (no scale anchor)"
NO_SCALE_LINK = "no scale information across a keyframe link (no landmark seen in three keyframes across it)"


def _no_scale_reason(H_t: np.ndarray, lam_max: float, translations: np.ndarray) -> str:
    """Why ``H_t`` has a null direction: the scale of the whole chain is free (nothing anchors
    it), or only the lengths of some links are (the scale is not carried across them)."""
    t = np.asarray(translations, dtype=np.float64).ravel()
    norm = float(np.linalg.norm(t))
    if norm == 0.0 or float(t @ H_t @ t) / (norm * norm) <= UNANCHORED_REL * lam_max:
        return NO_SCALE_ANCHOR
    return NO_SCALE_LINK


def keyframe_system(window: SlidingWindow, include_scale_fix: bool = True) -> KeyframeSystem:
    """The window's information over its keyframes (see :class:`KeyframeSystem`): only
    observations made in keyframes, landmarks eliminated; the marginalisation prior, the
    no-motion terms and (``include_scale_fix``) the scale fix of Eq. 9 over all window frames,
    with the non-keyframe frames marginalised out of them."""
    return _system_of_snapshot(_snapshot(window, include_scale_fix))


@dataclasses.dataclass
class _Snapshot:
    """What :func:`keyframe_system` reads of a window, copied (the packed problem holds copies
    of the landmark states and observations; the prior and the scale fix are replaced, never
    changed, by the window)."""

    frame_ids: tuple[int, ...]
    problem: WindowProblem
    cost: WindowCost
    scale_fix_included: bool


def _snapshot(window: SlidingWindow, include_scale_fix: bool) -> _Snapshot:
    kfs = tuple(window.keyframe_ids)
    # every landmark with its observations made in keyframes; one seen in its host only
    # contributes nothing after its elimination (the kernel skips it cheaply, cheaper than
    # selecting the landmarks seen in a second keyframe beforehand)
    problem = window.problem(None, target_filter=set(kfs))
    cost = window.cost_terms()
    if not include_scale_fix:
        cost.scale_fix = None
    return _Snapshot(kfs, problem, cost, cost.scale_fix is not None)


def _system_of_snapshot(snap: _Snapshot) -> KeyframeSystem:
    problem, cost, kfs = snap.problem, snap.cost, snap.frame_ids
    _, red = cost.linearize(problem, with_rhs=False)  # the information matrix only
    H_red = red.H
    (H_p, _, _), (H_s, _, _), (H_n, _, _) = cost.prior_terms(
        problem, cost.no_motion_pairs(problem), with_rhs=False)
    idx = [problem.index[f] for f in kfs]
    is_kf = np.zeros((len(problem.frame_ids), 6), dtype=bool)
    is_kf[idx] = True
    rows, others = np.flatnonzero(is_kf.ravel()), np.flatnonzero(~is_kf.ravel())
    H_pr = H_p + H_s + H_n
    if np.any(H_pr[others]):
        H_priors, _ = marginalize_dense(H_pr, np.zeros(H_pr.shape[0]), rows, others)
    else:  # no pose term on a non-keyframe: nothing to marginalise
        H_priors = H_pr[np.ix_(rows, rows)]
    return KeyframeSystem(
        frame_ids=kfs,
        poses=problem.poses[idx].copy(),
        poses_lin=problem.poses_lin[idx].copy(),
        H_reprojection=H_red[np.ix_(rows, rows)],
        H_priors=H_priors,
        scale_fix_included=snap.scale_fix_included,
    )


def scale_drift_of_system(system: KeyframeSystem) -> ScaleDriftResult:
    """Λ and Λ_ref of a :class:`KeyframeSystem`. The chain Jacobian is evaluated at the points
    the information was linearised at (``poses_lin``), so the window's gauge directions are
    exactly the oldest keyframe's absolute pose; the translations of Eq. 17 are the current
    estimates."""
    n = len(system.frame_ids)
    if n < MIN_KEYFRAMES:
        return ScaleDriftResult(None, None, n, reason=f"fewer than {MIN_KEYFRAMES} keyframes")
    H = system.H
    if not (np.all(np.isfinite(H)) and np.all(np.isfinite(system.poses_lin))):
        return ScaleDriftResult(None, None, n, reason="non-finite information or poses")
    H_t = relative_translation_information(H, system.poses_lin)
    translations = relative_poses(system.poses)[:, :3, 3]
    value, value_ref, lam_min, lam_max, reason = indicator_from_information(
        H_t, translations, relative_poses(system.poses_lin)[:, :3, 3])
    mean_t = float(np.mean(np.linalg.norm(translations, axis=1)))
    return ScaleDriftResult(value, value_ref, n, lam_min, lam_max, mean_t, reason)


def scale_drift_indicator(window: SlidingWindow, include_scale_fix: bool = True
                          ) -> ScaleDriftResult:
    """Λ_scaledrift of the window at its current estimate (call it at the final estimate of a
    frame: after the optimisation, the keyframe decision and outlier removal, before
    marginalisation). ``include_scale_fix``: whether the scale fix of Eq. 9 counts while it is
    in the window (the reference leaves it out; see docs/backend.md for the measurement)."""
    return scale_drift_task(window, include_scale_fix)()


def scale_drift_task(window: SlidingWindow, include_scale_fix: bool = True,
                     workspaces: WorkspacePool | None = None) -> Callable[[], ScaleDriftResult]:
    """:func:`scale_drift_indicator` in two parts: the window's state is packed (copied) now,
    and the returned callable computes Λ from that copy alone, so the window may change before
    it runs and it may run on another thread (its kernels release the GIL). ``workspaces``:
    the linearisation buffers of the computation (default the window's; give a pool of its
    own to a computation that may overlap the window's next optimisation, and run the
    callables of one pool one at a time). Numpy floating-point warnings are suppressed inside
    (every non-finite result is caught and reported as "not defined"), so a computation on
    another thread issues none."""
    kfs = window.keyframe_ids
    if len(kfs) < MIN_KEYFRAMES:
        result = ScaleDriftResult(None, None, len(kfs),
                                  reason=f"fewer than {MIN_KEYFRAMES} keyframes")
        return lambda: result
    snap = _snapshot(window, include_scale_fix)

    def compute() -> ScaleDriftResult:
        if workspaces is not None:
            snap.problem.workspace = workspaces.view(snap.problem.packed.num_observations)
        with np.errstate(all="ignore"):
            return scale_drift_of_system(_system_of_snapshot(snap))

    return compute
