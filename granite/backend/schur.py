"""Normal equations of the window: landmark elimination (Schur complement) and dense solves.

Conventions: the cost is ``E = sum r^T W r`` and the normal equations are ``H dx = -b`` with
``H = J^T W J`` and ``b = J^T W r`` (no factor 1/2). Pose ``k`` owns rows ``6k:6k+6`` of the
dense pose system, ordered ``[v, w]`` (decoupled twist of paper Eq. 14); each landmark owns a
3x3 block over ``[s_x, s_y, d]``, eliminated by orthogonal projection of its weighted
Jacobian rows (thin QR, :func:`schur_reduce`).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.linalg


@numba.njit(cache=True, nogil=True, inline="always")
def _add_jtwj(Hb: np.ndarray, i: int, j: int, wJa: np.ndarray, b0, b1) -> None:
    """``Hb[i, j] += wJa^T Jb`` for 2x6 Jacobians (block layout (K,K,6,6)), the rows of ``Jb``
    given as 6-tuples ``b0``, ``b1`` (see :func:`_row6`). Inlined into :func:`schur_reduce`
    (LLVM left it a call: 5 % of that kernel)."""
    for c1 in range(6):
        a0 = wJa[0, c1]
        a1 = wJa[1, c1]
        for c2 in range(6):
            Hb[i, j, c1, c2] += a0 * b0[c2] + a1 * b1[c2]


@numba.njit(cache=True, nogil=True, inline="always")
def _add_jtwj_lower(Hb: np.ndarray, i: int, wJa: np.ndarray, b0, b1) -> None:
    """The entries ``c2 <= c1`` of ``Hb[i, i] += wJa^T Jb`` (rows ``b0``, ``b1``): the only
    entries of a diagonal block that :func:`schur_reduce` assembles into ``H`` (its mirror
    loop writes the lower triangle last)."""
    for c1 in range(6):
        a0 = wJa[0, c1]
        a1 = wJa[1, c1]
        for c2 in range(c1 + 1):
            Hb[i, i, c1, c2] += a0 * b0[c2] + a1 * b1[c2]


#: A landmark column whose part orthogonal to the previous columns (thin QR of the
#: weighted landmark Jacobian) is at most this fraction of its norm is linearly dependent on
#: them to float64 round-off (a few hundred ulps): that coordinate is unconstrained and is held
#: (not eliminated, zero step), which gives the pseudo-inverse Schur complement. Not a setting.
DEPENDENT_COLUMN_REL = 1e-12


@numba.njit(cache=True, nogil=True)
def _landmark_qr(Al: np.ndarray, nr: int, Q: np.ndarray, Hll_inv: np.ndarray,
                 R: np.ndarray, Rinv: np.ndarray, cols: np.ndarray, with_inverse: bool) -> int:
    """Thin QR of the weighted landmark Jacobian ``Al[:nr]`` (nr x 3, damping rows included)
    by classical Gram-Schmidt with one re-orthogonalisation pass (CGS2: orthonormal to
    round-off whatever the conditioning). Writes ``Q[:nr, :3]``, an orthonormal basis of the
    column space in its first ``rank`` columns (the others zero), and (``with_inverse``)
    ``Hll_inv`` = ``(Al^T Al)^-1`` computed as ``R^-1 R^-T`` on the independent columns (zero rows and
    columns for a dependent one, see :data:`DEPENDENT_COLUMN_REL`). Returns the rank.
    ``R``, ``Rinv`` (3,3) and ``cols`` (3,) are workspaces."""
    for c in range(3):
        for r in range(nr):
            Q[r, c] = 0.0
    R[:, :] = 0.0
    p = 0
    for j in range(3):
        full = 0.0
        for r in range(nr):
            x = Al[r, j]
            Q[r, p] = x
            full += x * x
        if full == 0.0:
            continue
        for _ in range(2):
            for a in range(p):
                s = 0.0
                for r in range(nr):
                    s += Q[r, a] * Q[r, p]
                R[a, p] += s
                for r in range(nr):
                    Q[r, p] -= s * Q[r, a]
        nn = 0.0
        for r in range(nr):
            nn += Q[r, p] * Q[r, p]
        norm = np.sqrt(nn)
        if norm <= DEPENDENT_COLUMN_REL * np.sqrt(full):
            for a in range(p):
                R[a, p] = 0.0
            for r in range(nr):
                Q[r, p] = 0.0
            continue
        R[p, p] = norm
        inv_norm = 1.0 / norm
        for r in range(nr):
            Q[r, p] *= inv_norm
        cols[p] = j
        p += 1
    rank = p
    if not with_inverse:
        return rank
    # Rinv = R^-1 (upper triangular), Hll_inv = Rinv Rinv^T scattered onto the columns
    Rinv[:, :] = 0.0
    for c in range(rank - 1, -1, -1):
        Rinv[c, c] = 1.0 / R[c, c]
        for a in range(c - 1, -1, -1):
            s = 0.0
            for m in range(a + 1, c + 1):
                s += R[a, m] * Rinv[m, c]
            Rinv[a, c] = -s / R[a, a]
    for a in range(3):
        for b in range(3):
            Hll_inv[a, b] = 0.0
    for a in range(rank):
        for b in range(rank):
            s = 0.0
            for m in range(max(a, b), rank):
                s += Rinv[a, m] * Rinv[b, m]
            Hll_inv[cols[a], cols[b]] = s
    return rank


@numba.njit(cache=True, nogil=True, inline="always")
def _row6(A, i, q):
    """``A[i, q, :6]`` as a tuple of values. Read this way, LLVM keeps them in registers: a
    store into another array cannot alias them, so the accumulation loops that read them need
    no reloads and vectorise (``schur_reduce`` 1.45 -> 1.21 ms on captured spiral windows,
    the same bits)."""
    return (A[i, q, 0], A[i, q, 1], A[i, q, 2], A[i, q, 3], A[i, q, 4], A[i, q, 5])


@numba.njit(cache=True, nogil=True)
def schur_reduce(num_poses: int, lm_ptr: np.ndarray, lm_host: np.ndarray, obs_tgt: np.ndarray,
                 r: np.ndarray, w: np.ndarray, J_h: np.ndarray, J_t: np.ndarray,
                 J_l: np.ndarray, damping: float, lm_lambda: float, with_rhs: bool = True):
    """Accumulate the normal equations of all observations and eliminate the landmarks.

    Returns ``(H_raw, b_raw, H_red, b_red, Hll_inv, b_l)``: the pose-pose block and pose
    gradient before elimination (6K,6K), (6K,), the reduced camera system after it, the
    inverses of the (damped) landmark blocks (M,3,3) and the landmark gradients (M,3).
    ``damping + lm_lambda * diag`` is added to each landmark block before inversion.
    ``with_rhs=False``: only the matrices (``H_raw``, ``H_red``) are computed; the gradients
    and ``Hll_inv`` are returned as zeros (what Λ_scaledrift needs, 13 % less work).

    Elimination by orthogonal projection, not by inverting the 3x3 normal block: per landmark
    the weighted Jacobian rows ``[A_p | A_l]`` (``sqrt(w)`` times the 2x6 / 2x3 blocks, plus
    3 rows ``sqrt(damping + lm_lambda diag)`` in ``A_l`` and zero in ``A_p``) give the thin
    QR ``A_l = Q R`` (Gram-Schmidt with re-orthogonalisation) and ``G = Q^T A_p``; the landmark's Schur term is
    ``H_pl H_ll^-1 H_lp = G^T G`` and ``H_pl H_ll^-1 b_l = G^T Q^T r``. ``Q`` is orthonormal
    to round-off whatever the conditioning of ``A_l``, so ``H_raw - G^T G`` is the reduced
    system of a Jacobian within round-off of the true one (positive semi-definite up to
    ``eps |H|``); the 3x3 inverse of ``A_l^T A_l`` instead squares the condition number and
    made the reduced system indefinite on near-singular landmark blocks (a landmark with a
    single observation outside its host: rank 2 plus the damping; docs/backend.md).
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
    max_obs = 0
    for i in range(m):
        max_obs = max(max_obs, lm_ptr[i + 1] - lm_ptr[i])
    nr_max = 2 * max_obs + 3
    Al = np.zeros((nr_max, 3))
    Q = np.zeros((nr_max, 3))
    row_obs = np.empty(max_obs, dtype=np.int64)
    slot = -np.ones(num_poses, dtype=np.int64)
    slot_pose = np.empty(num_poses, dtype=np.int64)
    G = np.zeros((num_poses, 3, 6))
    diag = np.zeros(3)
    bli = np.zeros(3)
    qr_ = np.zeros(3)
    wJh = np.zeros((2, 6))
    wJt = np.zeros((2, 6))
    inv = np.zeros((3, 3))
    qr_R = np.zeros((3, 3))
    qr_Rinv = np.zeros((3, 3))
    qr_cols = np.zeros(3, dtype=np.int64)
    sqw = np.empty(max_obs)
    for i in range(m):
        h = lm_host[i]
        ns = 0
        no = 0
        diag[:] = 0.0
        bli[:] = 0.0
        for k in range(lm_ptr[i], lm_ptr[i + 1]):
            wk = w[k]
            if wk == 0.0:
                continue
            sk = np.sqrt(wk)
            for a in range(2):
                for c in range(3):
                    Al[2 * no + a, c] = sk * J_l[k, a, c]
            row_obs[no] = k
            sqw[no] = sk
            no += 1
            for c1 in range(3):
                if with_rhs:
                    bli[c1] += wk * (J_l[k, 0, c1] * r[k, 0] + J_l[k, 1, c1] * r[k, 1])
                diag[c1] += wk * (J_l[k, 0, c1] * J_l[k, 0, c1] + J_l[k, 1, c1] * J_l[k, 1, c1])
            t = obs_tgt[k]
            if t == h:
                continue
            if slot[h] < 0:
                slot[h] = ns
                slot_pose[ns] = h
                ns += 1
            if slot[t] < 0:
                slot[t] = ns
                slot_pose[ns] = t
                ns += 1
            h0 = _row6(J_h, k, 0)
            h1 = _row6(J_h, k, 1)
            t0 = _row6(J_t, k, 0)
            t1 = _row6(J_t, k, 1)
            for c in range(6):
                wJh[0, c] = wk * h0[c]
                wJh[1, c] = wk * h1[c]
                wJt[0, c] = wk * t0[c]
                wJt[1, c] = wk * t1[c]
            oh = 6 * h
            ot = 6 * t
            if with_rhs:
                for c1 in range(6):
                    b[oh + c1] += wJh[0, c1] * r[k, 0] + wJh[1, c1] * r[k, 1]
                    b[ot + c1] += wJt[0, c1] * r[k, 0] + wJt[1, c1] * r[k, 1]
            _add_jtwj_lower(Hb, h, wJh, h0, h1)
            _add_jtwj_lower(Hb, t, wJt, t0, t1)
            if h < t:
                _add_jtwj(Hb, h, t, wJh, t0, t1)
            else:
                _add_jtwj(Hb, t, h, wJt, h0, h1)
        b_l[i, :] = bli
        nr = 2 * no + 3
        for c in range(3):
            for c2 in range(3):
                Al[2 * no + c, c2] = 0.0
            Al[2 * no + c, c] = np.sqrt(damping + lm_lambda * diag[c])
        rank = _landmark_qr(Al, nr, Q, inv, qr_R, qr_Rinv, qr_cols, with_rhs)
        Hll_inv[i, :, :] = inv
        if ns == 0 or rank == 0:
            for a in range(ns):
                slot[slot_pose[a]] = -1
            continue
        # G_slot = Q^T A_p[:, slot] and Q^T r over the observation rows (damping rows: A_p = 0;
        # the columns of Q beyond the rank are zero)
        for a in range(ns):
            for q in range(3):
                for c in range(6):
                    G[a, q, c] = 0.0
        qr_[:] = 0.0
        sh = slot[h]
        for o in range(no):
            k = row_obs[o]
            sk = sqw[o]
            t = obs_tgt[k]
            st = slot[t]
            h0 = _row6(J_h, k, 0)
            h1 = _row6(J_h, k, 1)
            t0 = _row6(J_t, k, 0)
            t1 = _row6(J_t, k, 1)
            for q in range(3):
                q0 = Q[2 * o, q] * sk
                q1 = Q[2 * o + 1, q] * sk
                if with_rhs:
                    qr_[q] += q0 * r[k, 0] + q1 * r[k, 1]
                if t == h:
                    continue
                for c in range(6):
                    G[sh, q, c] += q0 * h0[c] + q1 * h1[c]
                    G[st, q, c] += q0 * t0[c] + q1 * t1[c]
        for a in range(ns if with_rhs else 0):
            oa = 6 * slot_pose[a]
            for c1 in range(6):
                sb[oa + c1] += G[a, 0, c1] * qr_[0] + G[a, 1, c1] * qr_[1] + G[a, 2, c1] * qr_[2]
        for a in range(ns):
            pa = slot_pose[a]
            for c in range(ns):
                pc = slot_pose[c]
                if pa > pc:
                    continue
                g0 = _row6(G, c, 0)
                g1 = _row6(G, c, 1)
                g2 = _row6(G, c, 2)
                if pa == pc:
                    # G_a^T G_a: entries (c1, c2) and (c2, c1) are the same products summed in
                    # the same order, so bit for bit equal: only c2 >= c1 is accumulated (the
                    # assembly below reads the other half from there)
                    for c1 in range(6):
                        x0 = G[a, 0, c1]
                        x1 = G[a, 1, c1]
                        x2 = G[a, 2, c1]
                        for c2 in range(c1, 6):
                            Sb[pa, pa, c1, c2] += x0 * g0[c2] + x1 * g1[c2] + x2 * g2[c2]
                    continue
                for c1 in range(6):
                    x0 = G[a, 0, c1]
                    x1 = G[a, 1, c1]
                    x2 = G[a, 2, c1]
                    for c2 in range(6):
                        Sb[pa, pc, c1, c2] += x0 * g0[c2] + x1 * g1[c2] + x2 * g2[c2]
        for a in range(ns):
            slot[slot_pose[a]] = -1
    H = np.empty((n6, n6))
    Hr = np.empty((n6, n6))
    for p1 in range(num_poses):
        for p2 in range(p1, num_poses):
            for c1 in range(6):
                for c2 in range(6):
                    # diagonal blocks: (c1, c2) and (c2, c1) write the same two entries and
                    # the later one, c1 > c2, stays: only that triangle of Hb is accumulated,
                    # and the landmark terms are kept on the other one (equal bit for bit)
                    if p1 == p2 and c1 < c2:
                        continue
                    x = Hb[p1, p2, c1, c2]
                    if p1 == p2 and c1 > c2:
                        y = x - Sb[p1, p1, c2, c1]
                    else:
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
