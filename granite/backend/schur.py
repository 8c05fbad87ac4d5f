"""Normal equations of the window: landmark elimination (Schur complement) and dense solves.

Conventions: the cost is ``E = sum r^T W r`` and the normal equations are ``H dx = -b`` with
``H = J^T W J`` and ``b = J^T W r`` (no factor 1/2). Pose ``k`` owns rows ``6k:6k+6`` of the
dense pose system, ordered ``[v, w]`` (decoupled twist of paper Eq. 14); each landmark owns a
3x3 block over ``[s_x, s_y, d]``.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.linalg


@numba.njit(cache=True, nogil=True)
def _spd_inverse3(A: np.ndarray, out: np.ndarray) -> None:
    """Inverse of a symmetric positive semi-definite 3x3 via LDL^T; directions with a pivot
    ``<= 1e-15 * max diag`` are treated as unconstrained (their inverse is set to 0). The
    threshold is float64 round-off, not a setting."""
    scale = max(A[0, 0], A[1, 1], A[2, 2])
    tol = 1e-15 * scale if scale > 0.0 else 1e-300
    L = np.zeros((3, 3))
    D = np.zeros(3)
    for j in range(3):
        s = A[j, j]
        for m in range(j):
            s -= L[j, m] * L[j, m] * D[m]
        D[j] = s
        L[j, j] = 1.0
        for i in range(j + 1, 3):
            s = A[i, j]
            for m in range(j):
                s -= L[i, m] * L[j, m] * D[m]
            L[i, j] = s / D[j] if D[j] > tol else 0.0
    # inverse = L^-T D^-1 L^-1
    Li = np.zeros((3, 3))
    for c in range(3):
        Li[c, c] = 1.0
        for i in range(c + 1, 3):
            s = 0.0
            for m in range(c, i):
                s -= L[i, m] * Li[m, c]
            Li[i, c] = s
    for i in range(3):
        for j in range(3):
            s = 0.0
            for m in range(3):
                if D[m] > tol:
                    s += Li[m, i] * Li[m, j] / D[m]
            out[i, j] = s


@numba.njit(cache=True, nogil=True)
def _add_jtwj(Hb: np.ndarray, i: int, j: int, wJa: np.ndarray, Jb: np.ndarray, k: int) -> None:
    """``Hb[i, j] += wJa^T Jb[k]`` for 2x6 Jacobians (block layout (K,K,6,6))."""
    for c1 in range(6):
        a0 = wJa[0, c1]
        a1 = wJa[1, c1]
        for c2 in range(6):
            Hb[i, j, c1, c2] += a0 * Jb[k, 0, c2] + a1 * Jb[k, 1, c2]


@numba.njit(cache=True, nogil=True)
def schur_reduce(num_poses: int, lm_ptr: np.ndarray, lm_host: np.ndarray, obs_tgt: np.ndarray,
                 r: np.ndarray, w: np.ndarray, J_h: np.ndarray, J_t: np.ndarray,
                 J_l: np.ndarray, damping: float, lm_lambda: float):
    """Accumulate the normal equations of all observations and eliminate the landmarks.

    Returns ``(H_raw, b_raw, H_red, b_red, Hll_inv, b_l)``: the pose-pose block and pose
    gradient before elimination (6K,6K), (6K,), the reduced camera system after it, the
    inverses of the (damped) landmark blocks (M,3,3) and the landmark gradients (M,3).
    ``damping + lm_lambda * diag`` is added to each landmark block before inversion.
    Accumulation uses 6x6 block storage and only blocks ``(i, j)`` with ``i <= j``.
    """
    n6 = 6 * num_poses
    Hb = np.zeros((num_poses, num_poses, 6, 6))
    Sb = np.zeros((num_poses, num_poses, 6, 6))
    b = np.zeros(n6)
    sb = np.zeros(n6)
    m = lm_ptr.shape[0] - 1
    Hll_inv = np.zeros((m, 3, 3))
    b_l = np.zeros((m, 3))
    slot = -np.ones(num_poses, dtype=np.int64)
    slot_pose = np.empty(num_poses, dtype=np.int64)
    Hpl = np.zeros((num_poses, 6, 3))
    A = np.zeros((num_poses, 6, 3))
    Hll = np.zeros((3, 3))
    bli = np.zeros(3)
    wJh = np.zeros((2, 6))
    wJt = np.zeros((2, 6))
    inv = np.zeros((3, 3))
    for i in range(m):
        h = lm_host[i]
        ns = 0
        Hll[:, :] = 0.0
        bli[:] = 0.0
        for k in range(lm_ptr[i], lm_ptr[i + 1]):
            wk = w[k]
            if wk == 0.0:
                continue
            for c1 in range(3):
                bli[c1] += wk * (J_l[k, 0, c1] * r[k, 0] + J_l[k, 1, c1] * r[k, 1])
                for c2 in range(c1, 3):
                    Hll[c1, c2] += wk * (J_l[k, 0, c1] * J_l[k, 0, c2]
                                         + J_l[k, 1, c1] * J_l[k, 1, c2])
            t = obs_tgt[k]
            if t == h:
                continue
            if slot[h] < 0:
                slot[h] = ns
                slot_pose[ns] = h
                Hpl[ns, :, :] = 0.0
                ns += 1
            if slot[t] < 0:
                slot[t] = ns
                slot_pose[ns] = t
                Hpl[ns, :, :] = 0.0
                ns += 1
            sh = slot[h]
            st = slot[t]
            for a in range(2):
                for c in range(6):
                    wJh[a, c] = wk * J_h[k, a, c]
                    wJt[a, c] = wk * J_t[k, a, c]
            oh = 6 * h
            ot = 6 * t
            for c1 in range(6):
                b[oh + c1] += wJh[0, c1] * r[k, 0] + wJh[1, c1] * r[k, 1]
                b[ot + c1] += wJt[0, c1] * r[k, 0] + wJt[1, c1] * r[k, 1]
                for c2 in range(3):
                    Hpl[sh, c1, c2] += wJh[0, c1] * J_l[k, 0, c2] + wJh[1, c1] * J_l[k, 1, c2]
                    Hpl[st, c1, c2] += wJt[0, c1] * J_l[k, 0, c2] + wJt[1, c1] * J_l[k, 1, c2]
            _add_jtwj(Hb, h, h, wJh, J_h, k)
            _add_jtwj(Hb, t, t, wJt, J_t, k)
            if h < t:
                _add_jtwj(Hb, h, t, wJh, J_t, k)
            else:
                _add_jtwj(Hb, t, h, wJt, J_h, k)
        for c1 in range(3):
            for c2 in range(c1):
                Hll[c1, c2] = Hll[c2, c1]
        for c in range(3):
            Hll[c, c] += damping + lm_lambda * Hll[c, c]
        _spd_inverse3(Hll, inv)
        Hll_inv[i, :, :] = inv
        b_l[i, :] = bli
        for a in range(ns):
            pa = slot_pose[a]
            oa = 6 * pa
            for c1 in range(6):
                for c2 in range(3):
                    A[a, c1, c2] = (Hpl[a, c1, 0] * inv[0, c2] + Hpl[a, c1, 1] * inv[1, c2]
                                    + Hpl[a, c1, 2] * inv[2, c2])
                sb[oa + c1] += A[a, c1, 0] * bli[0] + A[a, c1, 1] * bli[1] + A[a, c1, 2] * bli[2]
        for a in range(ns):
            pa = slot_pose[a]
            for c in range(ns):
                pc = slot_pose[c]
                if pa > pc:
                    continue
                for c1 in range(6):
                    x0 = A[a, c1, 0]
                    x1 = A[a, c1, 1]
                    x2 = A[a, c1, 2]
                    for c2 in range(6):
                        Sb[pa, pc, c1, c2] += (x0 * Hpl[c, c2, 0] + x1 * Hpl[c, c2, 1]
                                               + x2 * Hpl[c, c2, 2])
        for a in range(ns):
            slot[slot_pose[a]] = -1
    H = np.empty((n6, n6))
    Hr = np.empty((n6, n6))
    for p1 in range(num_poses):
        for p2 in range(p1, num_poses):
            for c1 in range(6):
                for c2 in range(6):
                    x = Hb[p1, p2, c1, c2]
                    y = x - Sb[p1, p2, c1, c2]
                    H[6 * p1 + c1, 6 * p2 + c2] = x
                    H[6 * p2 + c2, 6 * p1 + c1] = x
                    Hr[6 * p1 + c1, 6 * p2 + c2] = y
                    Hr[6 * p2 + c2, 6 * p1 + c1] = y
    return H, b, Hr, b - sb, Hll_inv, b_l


@numba.njit(cache=True, nogil=True)
def back_substitute(dx: np.ndarray, lm_ptr: np.ndarray, lm_host: np.ndarray,
                    obs_tgt: np.ndarray, w: np.ndarray, J_h: np.ndarray, J_t: np.ndarray,
                    J_l: np.ndarray, Hll_inv: np.ndarray, b_l: np.ndarray) -> np.ndarray:
    """Landmark increments ``dl_i = -Hll_i^-1 (b_l_i + H_lp dx)`` (M,3) for pose step ``dx``."""
    m = lm_ptr.shape[0] - 1
    dl = np.zeros((m, 3))
    acc = np.zeros(3)
    for i in range(m):
        h = lm_host[i]
        acc[:] = b_l[i, :]
        for k in range(lm_ptr[i], lm_ptr[i + 1]):
            t = obs_tgt[k]
            wk = w[k]
            if wk == 0.0 or t == h:
                continue
            for a in range(2):
                jx = 0.0
                for c in range(6):
                    jx += J_h[k, a, c] * dx[6 * h + c] + J_t[k, a, c] * dx[6 * t + c]
                for c in range(3):
                    acc[c] += wk * J_l[k, a, c] * jx
        for c in range(3):
            dl[i, c] = -(Hll_inv[i, c, 0] * acc[0] + Hll_inv[i, c, 1] * acc[1]
                         + Hll_inv[i, c, 2] * acc[2])
    return dl


def solve_normal_equations(H: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Step ``dx = -H^-1 b`` of a symmetric positive (semi-)definite system.

    Jacobi-scaled Cholesky; if the matrix is not numerically positive definite, a growing
    relative diagonal regulariser is added (1e-12, then x100, 12 attempts) until the
    factorisation succeeds: a numerical safeguard for (nearly) singular systems, not
    a setting. Rows with a zero diagonal get a zero step.
    """
    diag = np.diag(H).copy()
    active = diag > 0.0
    dx = np.zeros_like(b)
    if not np.any(active):
        return dx
    idx = np.flatnonzero(active)
    Ha = H[np.ix_(idx, idx)]
    scale = 1.0 / np.sqrt(diag[idx])
    Hs = Ha * scale[:, None] * scale[None, :]
    bs = b[idx] * scale
    reg = 0.0
    for _ in range(12):
        try:
            factor = scipy.linalg.cho_factor(Hs + reg * np.eye(len(idx)), lower=False,
                                             check_finite=False)
            dx[idx] = -scale * scipy.linalg.cho_solve(factor, bs, check_finite=False)
            if np.all(np.isfinite(dx)):
                return dx
        except np.linalg.LinAlgError:
            pass
        reg = 1e-12 if reg == 0.0 else reg * 100.0
    raise np.linalg.LinAlgError("normal equations could not be factorised")
