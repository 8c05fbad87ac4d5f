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
from scipy.linalg.lapack import dpotrf as _potrf, dpotrs as _potrs

from granite.geometry import hat


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


@numba.njit(cache=True, nogil=True, inline="always")
def _add_block(A: np.ndarray, p: int, q: int, B: np.ndarray) -> None:
    """Add the 6x6 block ``B`` at absolute block ``(p, q)`` of the upper block storage
    ``A`` (K,K,6,6), i.e. ``B^T`` at ``(q, p)`` when ``p > q``."""
    if p <= q:
        for c1 in range(6):
            for c2 in range(6):
                A[p, q, c1, c2] += B[c1, c2]
    else:
        for c1 in range(6):
            for c2 in range(6):
                A[q, p, c2, c1] += B[c1, c2]


@numba.njit(cache=True, nogil=True, inline="always")
def _times_m(S: np.ndarray, d0: float, d1: float, d2: float, out: np.ndarray) -> None:
    """``out = S M`` for a 6x6 ``S`` and the relative map ``M = [[-I, [d]x], [0, -I]]``
    (:func:`relative_map`): row ``u = S[r, :3]`` gives ``[-u, u x d - S[r, 3:]]``."""
    for r in range(6):
        u0 = S[r, 0]
        u1 = S[r, 1]
        u2 = S[r, 2]
        out[r, 0] = -u0
        out[r, 1] = -u1
        out[r, 2] = -u2
        out[r, 3] = u1 * d2 - u2 * d1 - S[r, 3]
        out[r, 4] = u2 * d0 - u0 * d2 - S[r, 4]
        out[r, 5] = u0 * d1 - u1 * d0 - S[r, 5]


@numba.njit(cache=True, nogil=True, inline="always")
def _mt_times(Y: np.ndarray, d0: float, d1: float, d2: float, out: np.ndarray) -> None:
    """``out = M^T Y`` (see :func:`_times_m`): column ``y = Y[:3, c]`` gives
    ``[-y, y x d - Y[3:, c]]``."""
    for c in range(6):
        y0 = Y[0, c]
        y1 = Y[1, c]
        y2 = Y[2, c]
        out[0, c] = -y0
        out[1, c] = -y1
        out[2, c] = -y2
        out[3, c] = y1 * d2 - y2 * d1 - Y[3, c]
        out[4, c] = y2 * d0 - y0 * d2 - Y[4, c]
        out[5, c] = y0 * d1 - y1 * d0 - Y[5, c]


def relative_map(t_w_h: np.ndarray, t_w_t: np.ndarray) -> np.ndarray:
    """The 6x6 ``M`` with ``J_t = J_h M`` for an observation hosted by frame ``h`` and seen in
    frame ``t`` (camera centres ``t_w_h``, ``t_w_t`` at the linearisation point): with
    ``d = t_w_h - t_w_t``, ``M = [[-I, [d]x], [0, -I]]`` on the twist ``[v, w]``
    (docs/backend.md, "Relative-pose elimination"). The pixel residual then depends on the two
    poses through ``delta = dx_h + M dx_t`` only."""
    M = -np.eye(6)
    M[:3, 3:] = hat(np.asarray(t_w_h, dtype=float) - np.asarray(t_w_t, dtype=float))
    return M


@numba.njit(cache=True, nogil=True)
def _expand_host(h: int, targets: np.ndarray, nt: int, R: np.ndarray, diagonal_only: bool,
                 t_lin: np.ndarray, A: np.ndarray, col: np.ndarray, tmp: np.ndarray,
                 tmp2: np.ndarray) -> None:
    """Add ``P^T R P`` to the absolute upper block storage ``A`` (K,K,6,6): ``R`` (K,K,6,6)
    is a symmetric block matrix over the relative increments ``delta_t = dx_h + M_t dx_t``
    of host ``h`` and its targets ``targets[:nt]`` (blocks ``R[t1, t2]`` with ``t1 <= t2``
    stored, full 6x6), ``diagonal_only``: only its diagonal blocks are non-zero. Blocks:
    ``(h, h) += sum R[t1, t2]``, ``(h, t2) += (sum_t1 R[t1, t2]) M_t2``,
    ``(t1, t2) += M_t1^T R[t1, t2] M_t2``."""
    hh = np.zeros((6, 6))
    for b in range(nt):
        t2 = targets[b]
        col[:, :] = 0.0
        if diagonal_only:
            col[:, :] = R[t2, t2]
        else:
            for a in range(nt):
                t1 = targets[a]
                if t1 <= t2:
                    for c1 in range(6):
                        for c2 in range(6):
                            col[c1, c2] += R[t1, t2, c1, c2]
                else:
                    for c1 in range(6):
                        for c2 in range(6):
                            col[c1, c2] += R[t2, t1, c2, c1]
        for c1 in range(6):
            for c2 in range(6):
                hh[c1, c2] += col[c1, c2]
        d0 = t_lin[h, 0] - t_lin[t2, 0]
        d1 = t_lin[h, 1] - t_lin[t2, 1]
        d2 = t_lin[h, 2] - t_lin[t2, 2]
        _times_m(col, d0, d1, d2, tmp)
        _add_block(A, h, t2, tmp)
        for a in range(nt):
            t1 = targets[a]
            if t1 > t2 or (diagonal_only and t1 != t2):
                continue
            _times_m(R[t1, t2], d0, d1, d2, tmp)
            _mt_times(tmp, t_lin[h, 0] - t_lin[t1, 0], t_lin[h, 1] - t_lin[t1, 1],
                      t_lin[h, 2] - t_lin[t1, 2], tmp2)
            _add_block(A, t1, t2, tmp2)
    _add_block(A, h, h, hh)


@numba.njit(cache=True, nogil=True)
def schur_reduce(num_poses: int, lm_ptr: np.ndarray, lm_host: np.ndarray, obs_tgt: np.ndarray,
                 r: np.ndarray, w: np.ndarray, J_h: np.ndarray, J_l: np.ndarray,
                 t_lin: np.ndarray, damping: float, lm_lambda: float, with_rhs: bool = True):
    """Accumulate the normal equations of all observations and eliminate the landmarks.

    Returns ``(H_raw, b_raw, H_red, b_red, Hll_inv, b_l)``: the pose-pose block and pose
    gradient before elimination (6K,6K), (6K,), the reduced camera system after it, the
    inverses of the (damped) landmark blocks (M,3,3) and the landmark gradients (M,3).
    ``damping + lm_lambda * diag`` is added to each landmark block before inversion.
    ``with_rhs=False``: only the matrices (``H_raw``, ``H_red``) are computed; the gradients
    and ``Hll_inv`` are returned as zeros (what Λ_scaledrift needs).

    Relative-pose form: an observation's Jacobian w.r.t. its host's and target's twists is
    ``[J_h, J_h M_ht]`` (:func:`relative_map`, ``t_lin`` (K,3) the camera centres at the
    linearisation points), so it sees the poses through ``delta_ht = dx_h + M_ht dx_t`` only.
    The landmarks of one host are eliminated over those relative increments of their targets
    (one 6-column block per target instead of two), and each host's relative system is mapped
    to the absolute poses once (:func:`_expand_host`): half the per-observation products.

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
    The output is exactly symmetric (upper block storage, mirrored).
    """
    K = num_poses
    n6 = 6 * K
    m = lm_ptr.shape[0] - 1
    # landmarks grouped by host (stable counting sort)
    count = np.zeros(K + 1, dtype=np.int64)
    for i in range(m):
        count[lm_host[i] + 1] += 1
    for p in range(K):
        count[p + 1] += count[p]
    order = np.empty(m, dtype=np.int64)
    fill = count[:K].copy()
    for i in range(m):
        order[fill[lm_host[i]]] = i
        fill[lm_host[i]] += 1
    # absolute accumulators (upper block storage) and one host's relative system
    Ha = np.zeros((K, K, 6, 6))
    Sa = np.zeros((K, K, 6, 6))
    b = np.zeros(n6)
    sb = np.zeros(n6)
    Hr = np.zeros((K, K, 6, 6))
    Sr = np.zeros((K, K, 6, 6))
    br = np.zeros((K, 6))
    sbr = np.zeros((K, 6))
    host_targets = np.empty(K, dtype=np.int64)
    in_host = np.zeros(K, dtype=np.bool_)
    Hll_inv = np.zeros((m, 3, 3))
    b_l = np.zeros((m, 3))
    max_obs = 0
    for i in range(m):
        max_obs = max(max_obs, lm_ptr[i + 1] - lm_ptr[i])
    nr_max = 2 * max_obs + 3
    Al = np.zeros((nr_max, 3))
    Q = np.zeros((nr_max, 3))
    row_obs = np.empty(max_obs, dtype=np.int64)
    slot = -np.ones(K, dtype=np.int64)
    slot_pose = np.empty(K, dtype=np.int64)
    G = np.zeros((K, 3, 6))
    diag = np.zeros(3)
    bli = np.zeros(3)
    qr_ = np.zeros(3)
    inv = np.zeros((3, 3))
    qr_R = np.zeros((3, 3))
    qr_Rinv = np.zeros((3, 3))
    qr_cols = np.zeros(3, dtype=np.int64)
    sqw = np.empty(max_obs)
    col = np.zeros((6, 6))
    tmp = np.zeros((6, 6))
    tmp2 = np.zeros((6, 6))
    for h in range(K):
        nh = 0  # targets of this host's landmarks
        for oi in range(count[h], count[h + 1]):
            i = order[oi]
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
                if slot[t] < 0:
                    slot[t] = ns
                    slot_pose[ns] = t
                    ns += 1
                if not in_host[t]:
                    in_host[t] = True
                    host_targets[nh] = t
                    nh += 1
                j0 = _row6(J_h, k, 0)
                j1 = _row6(J_h, k, 1)
                if with_rhs:
                    r0 = wk * r[k, 0]
                    r1 = wk * r[k, 1]
                    for c1 in range(6):
                        br[t, c1] += j0[c1] * r0 + j1[c1] * r1
                for c1 in range(6):
                    a0 = wk * j0[c1]
                    a1 = wk * j1[c1]
                    for c2 in range(6):
                        Hr[t, t, c1, c2] += a0 * j0[c2] + a1 * j1[c2]
            b_l[i, :] = bli
            if ns == 0 and not with_rhs:
                continue  # no pose term, and no landmark inverse wanted (Λ's systems)
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
            # G_slot = Q^T A_p[:, slot] and Q^T r over the observation rows (damping rows:
            # A_p = 0; the columns of Q beyond the rank are zero)
            for a in range(ns):
                for q in range(3):
                    for c in range(6):
                        G[a, q, c] = 0.0
            qr_[:] = 0.0
            for o in range(no):
                k = row_obs[o]
                sk = sqw[o]
                t = obs_tgt[k]
                j0 = _row6(J_h, k, 0)
                j1 = _row6(J_h, k, 1)
                for q in range(3):
                    q0 = Q[2 * o, q] * sk
                    q1 = Q[2 * o + 1, q] * sk
                    if with_rhs:
                        qr_[q] += q0 * r[k, 0] + q1 * r[k, 1]
                    if t == h:
                        continue
                    st = slot[t]
                    for c in range(6):
                        G[st, q, c] += q0 * j0[c] + q1 * j1[c]
            for a in range(ns if with_rhs else 0):
                ta = slot_pose[a]
                for c1 in range(6):
                    sbr[ta, c1] += G[a, 0, c1] * qr_[0] + G[a, 1, c1] * qr_[1] + G[a, 2, c1] * qr_[2]
            for a in range(ns):
                pa = slot_pose[a]
                for c in range(ns):
                    pc = slot_pose[c]
                    if pa > pc:
                        continue
                    g0 = _row6(G, c, 0)
                    g1 = _row6(G, c, 1)
                    g2 = _row6(G, c, 2)
                    for c1 in range(6):
                        x0 = G[a, 0, c1]
                        x1 = G[a, 1, c1]
                        x2 = G[a, 2, c1]
                        for c2 in range(6):
                            Sr[pa, pc, c1, c2] += x0 * g0[c2] + x1 * g1[c2] + x2 * g2[c2]
            for a in range(ns):
                slot[slot_pose[a]] = -1
        if nh == 0:
            continue
        # this host's relative systems to absolute poses
        _expand_host(h, host_targets, nh, Hr, True, t_lin, Ha, col, tmp, tmp2)
        _expand_host(h, host_targets, nh, Sr, False, t_lin, Sa, col, tmp, tmp2)
        for a in range(nh):
            t = host_targets[a]
            d0 = t_lin[h, 0] - t_lin[t, 0]
            d1 = t_lin[h, 1] - t_lin[t, 1]
            d2 = t_lin[h, 2] - t_lin[t, 2]
            if with_rhs:
                # b[h] += g, b[t] += M^T g with M^T g = [-g_v, g_v x d - g_w]
                for src, dst in ((br, b), (sbr, sb)):
                    g0 = src[t, 0]
                    g1 = src[t, 1]
                    g2 = src[t, 2]
                    for c in range(6):
                        dst[6 * h + c] += src[t, c]
                    dst[6 * t + 0] -= g0
                    dst[6 * t + 1] -= g1
                    dst[6 * t + 2] -= g2
                    dst[6 * t + 3] += g1 * d2 - g2 * d1 - src[t, 3]
                    dst[6 * t + 4] += g2 * d0 - g0 * d2 - src[t, 4]
                    dst[6 * t + 5] += g0 * d1 - g1 * d0 - src[t, 5]
                    for c in range(6):
                        src[t, c] = 0.0
            for a2 in range(nh):
                t2 = host_targets[a2]
                Hr[t, t2, :, :] = 0.0
                Sr[t, t2, :, :] = 0.0
        for a in range(nh):
            in_host[host_targets[a]] = False
    H = np.empty((n6, n6))
    Hred = np.empty((n6, n6))
    for p1 in range(K):
        for p2 in range(p1, K):
            for c1 in range(6):
                for c2 in range(6):
                    # diagonal blocks: the upper triangle (c1 <= c2) is mirrored
                    if p1 == p2 and c1 > c2:
                        continue
                    x = Ha[p1, p2, c1, c2]
                    y = x - Sa[p1, p2, c1, c2]
                    H[6 * p1 + c1, 6 * p2 + c2] = x
                    H[6 * p2 + c2, 6 * p1 + c1] = x
                    Hred[6 * p1 + c1, 6 * p2 + c2] = y
                    Hred[6 * p2 + c2, 6 * p1 + c1] = y
    return H, b, Hred, b - sb, Hll_inv, b_l


@numba.njit(cache=True, nogil=True)
def reduced_gradient(num_poses: int, lm_ptr: np.ndarray, lm_host: np.ndarray,
                     obs_tgt: np.ndarray, r: np.ndarray, w: np.ndarray, w_hess: np.ndarray,
                     J_h: np.ndarray, J_l: np.ndarray, t_lin: np.ndarray,
                     Hll_inv: np.ndarray):
    """The gradients of :func:`schur_reduce` for new residuals ``r`` and weights ``w`` with the
    Jacobians, Hessian weights ``w_hess`` and landmark inverses ``Hll_inv`` of an earlier
    call: ``(b_raw, b_red, b_l)`` with ``b_l_i = sum J_l^T w r``, ``b_raw = sum J_p^T w r``
    (6K,) and ``b_red = b_raw - sum_i H_pi Hll_inv_i b_l_i``, ``H_pi = sum J_p^T w_hess J_l``.
    With ``H`` of the earlier call, ``H dx = -b_red`` and :func:`back_substitute` (``w_hess``,
    ``b_l``) give the step that reuses its linearisation (``[backend] jacobian_reuse_steps``);
    with the same ``r``, ``w`` as that call it gives its ``b``."""
    K = num_poses
    m = lm_ptr.shape[0] - 1
    b = np.zeros(6 * K)
    sb = np.zeros(6 * K)
    b_l = np.zeros((m, 3))
    y = np.zeros(3)
    g = np.zeros(6)
    s = np.zeros(6)
    for i in range(m):
        h = lm_host[i]
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for k in range(lm_ptr[i], lm_ptr[i + 1]):
            wk = w[k]
            if wk == 0.0:
                continue
            r0 = wk * r[k, 0]
            r1 = wk * r[k, 1]
            g0 += J_l[k, 0, 0] * r0 + J_l[k, 1, 0] * r1
            g1 += J_l[k, 0, 1] * r0 + J_l[k, 1, 1] * r1
            g2 += J_l[k, 0, 2] * r0 + J_l[k, 1, 2] * r1
        b_l[i, 0] = g0
        b_l[i, 1] = g1
        b_l[i, 2] = g2
        for c in range(3):
            y[c] = Hll_inv[i, c, 0] * g0 + Hll_inv[i, c, 1] * g1 + Hll_inv[i, c, 2] * g2
        for k in range(lm_ptr[i], lm_ptr[i + 1]):
            t = obs_tgt[k]
            if t == h:
                continue
            wk = w[k]
            wh = w_hess[k]
            r0 = wk * r[k, 0]
            r1 = wk * r[k, 1]
            # J_l y per pixel row, weighted by the Hessian's weight
            e0 = wh * (J_l[k, 0, 0] * y[0] + J_l[k, 0, 1] * y[1] + J_l[k, 0, 2] * y[2])
            e1 = wh * (J_l[k, 1, 0] * y[0] + J_l[k, 1, 1] * y[1] + J_l[k, 1, 2] * y[2])
            for c in range(6):
                g[c] = J_h[k, 0, c] * r0 + J_h[k, 1, c] * r1
                s[c] = J_h[k, 0, c] * e0 + J_h[k, 1, c] * e1
            # host: += g, target: += M^T g = [-g_v, g_v x d - g_w] (d = t_h - t_t)
            d0 = t_lin[h, 0] - t_lin[t, 0]
            d1 = t_lin[h, 1] - t_lin[t, 1]
            d2 = t_lin[h, 2] - t_lin[t, 2]
            for src, dst in ((g, b), (s, sb)):
                for c in range(6):
                    dst[6 * h + c] += src[c]
                dst[6 * t + 0] -= src[0]
                dst[6 * t + 1] -= src[1]
                dst[6 * t + 2] -= src[2]
                dst[6 * t + 3] += src[1] * d2 - src[2] * d1 - src[3]
                dst[6 * t + 4] += src[2] * d0 - src[0] * d2 - src[4]
                dst[6 * t + 5] += src[0] * d1 - src[1] * d0 - src[5]
    return b, b - sb, b_l


@numba.njit(cache=True, nogil=True)
def back_substitute(dx: np.ndarray, lm_ptr: np.ndarray, lm_host: np.ndarray,
                    obs_tgt: np.ndarray, w: np.ndarray, J_h: np.ndarray, J_l: np.ndarray,
                    t_lin: np.ndarray, Hll_inv: np.ndarray, b_l: np.ndarray) -> np.ndarray:
    """Landmark increments ``dl_i = -Hll_i^-1 (b_l_i + H_lp dx)`` (M,3) for pose step ``dx``
    (the pose Jacobian of an observation is ``J_h`` times ``delta = dx_h + M_ht dx_t``,
    :func:`relative_map`)."""
    m = lm_ptr.shape[0] - 1
    dl = np.zeros((m, 3))
    acc = np.zeros(3)
    delta = np.zeros(6)
    for i in range(m):
        h = lm_host[i]
        acc[:] = b_l[i, :]
        for k in range(lm_ptr[i], lm_ptr[i + 1]):
            t = obs_tgt[k]
            wk = w[k]
            if wk == 0.0 or t == h:
                continue
            d0 = t_lin[h, 0] - t_lin[t, 0]
            d1 = t_lin[h, 1] - t_lin[t, 1]
            d2 = t_lin[h, 2] - t_lin[t, 2]
            # M dx_t = [-v + [d]x w, -w]
            v0 = dx[6 * t]
            v1 = dx[6 * t + 1]
            v2 = dx[6 * t + 2]
            w0 = dx[6 * t + 3]
            w1 = dx[6 * t + 4]
            w2 = dx[6 * t + 5]
            delta[0] = dx[6 * h] - v0 + d1 * w2 - d2 * w1
            delta[1] = dx[6 * h + 1] - v1 + d2 * w0 - d0 * w2
            delta[2] = dx[6 * h + 2] - v2 + d0 * w1 - d1 * w0
            delta[3] = dx[6 * h + 3] - w0
            delta[4] = dx[6 * h + 4] - w1
            delta[5] = dx[6 * h + 5] - w2
            for a in range(2):
                jx = 0.0
                for c in range(6):
                    jx += J_h[k, a, c] * delta[c]
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
    a setting. Rows with a zero diagonal get a zero step. LAPACK's ``dpotrf`` / ``dpotrs``
    are called directly: what ``scipy.linalg.cho_factor`` / ``cho_solve`` call, without their
    argument checks (a few hundred microseconds per frame on the estimator's thread).
    """
    diag = np.diag(H)
    active = diag > 0.0
    dx = np.zeros_like(b)
    n_active = int(np.count_nonzero(active))
    if n_active == 0:
        return dx
    if n_active == len(diag):  # the usual case: no selection, the same values
        idx = slice(None)
        Ha, d, ba = H, diag, b
    else:
        idx = np.flatnonzero(active)
        Ha, d, ba = H[np.ix_(idx, idx)], diag[idx], b[idx]
    scale = 1.0 / np.sqrt(d)
    Hs = Ha * scale[:, None] * scale[None, :]
    bs = ba * scale
    reg = 0.0
    for _ in range(12):
        factor, info = _potrf(Hs + reg * np.eye(n_active), lower=0, overwrite_a=1, clean=0)
        if info == 0:
            x, info = _potrs(factor, bs, lower=0, overwrite_b=0)
            if info != 0:
                raise ValueError(f"illegal value in argument {-info} of LAPACK's dpotrs")
            dx[idx] = -scale * x
            if np.all(np.isfinite(dx)):
                return dx
        elif info < 0:
            raise ValueError(f"illegal value in argument {-info} of LAPACK's dpotrf")
        reg = 1e-12 if reg == 0.0 else reg * 100.0
    raise np.linalg.LinAlgError("normal equations could not be factorised")
