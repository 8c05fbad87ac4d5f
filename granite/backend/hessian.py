"""Dense marginalisation helpers and the window's linearised pose system.

:class:`WindowHessian` is what the keyframe criterion (negative entropy, paper Eq. 10) and the
scale-drift indicator (paper Eq. 11-17) consume: the Gauss-Newton Hessian over the window's
poses with all landmarks eliminated by the Schur complement, split into its terms.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg


#: Numerical rank cut-off of :func:`_generalized_inverse`: eigenvalues of the Jacobi-scaled
#: matrix below this fraction of the largest are zero information (unconstrained directions,
#: e.g. the gauge). A property of float64 round-off (about 1e4 eps), not of the problem, so
#: not a setting.
_EIGENVALUE_REL_TOL = 1e-12


def _generalized_inverse(H: np.ndarray, rel_tol: float = _EIGENVALUE_REL_TOL) -> np.ndarray:
    """A generalised inverse of a symmetric PSD matrix: Jacobi scaling, then the eigenvalue
    pseudo-inverse with eigenvalues below ``rel_tol * max`` treated as zero."""
    n = H.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    d = np.diag(H).copy()
    scale = np.where(d > 0.0, 1.0 / np.sqrt(np.where(d > 0.0, d, 1.0)), 0.0)
    Hs = H * scale[:, None] * scale[None, :]
    Hs = 0.5 * (Hs + Hs.T)
    vals, vecs = np.linalg.eigh(Hs)
    top = vals.max() if vals.size else 0.0
    keep = vals > rel_tol * max(top, 0.0)
    inv_vals = np.where(keep, 1.0 / np.where(keep, vals, 1.0), 0.0)
    inv_s = (vecs * inv_vals) @ vecs.T
    return inv_s * scale[:, None] * scale[None, :]


def marginalize_dense(H: np.ndarray, b: np.ndarray, keep: np.ndarray, marg: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Schur complement: ``(H_kk - H_km H_mm^+ H_mk, b_k - H_km H_mm^+ b_m)`` for index arrays
    ``keep`` and ``marg``. Unconstrained directions of ``H_mm`` (zero information) are handled
    with a generalised inverse, which is exact for a PSD ``H``."""
    keep = np.asarray(keep, dtype=np.int64)
    marg = np.asarray(marg, dtype=np.int64)
    H_kk = H[np.ix_(keep, keep)]
    if marg.size == 0:
        return H_kk.copy(), b[keep].copy()
    H_km = H[np.ix_(keep, marg)]
    H_mm_inv = _generalized_inverse(H[np.ix_(marg, marg)])
    A = H_km @ H_mm_inv
    H_new = H_kk - A @ H_km.T
    return 0.5 * (H_new + H_new.T), b[keep] - A @ b[marg]


#: The Cholesky path of :func:`information_schur_complement` is taken when the Jacobi-scaled
#: block to eliminate has all squared pivots above this (its condition number is below about
#: 1e12, the rank cut-off of :func:`_generalized_inverse`); otherwise the generalised inverse.
_CHOLESKY_MIN_PIVOT2 = 1e-12


def information_schur_complement(H: np.ndarray, keep: np.ndarray, marg: np.ndarray) -> np.ndarray:
    """``H_kk - H_km H_mm^-1 H_mk`` (the information of ``keep`` with ``marg`` marginalised)
    by a Jacobi-scaled Cholesky factorisation of ``H_mm`` (a tenth of the eigen-decomposition's
    cost); :func:`marginalize_dense` (generalised inverse) when ``H_mm`` is singular or nearly
    so."""
    m = len(marg)
    order = np.concatenate([np.asarray(marg, dtype=np.int64), np.asarray(keep, dtype=np.int64)])
    H = H[np.ix_(order, order)]  # the marginalised variables first: slices below
    H_mm = H[:m, :m]
    d = np.diag(H_mm)
    if m and np.all(d > 0.0):
        sc = 1.0 / np.sqrt(d)
        try:
            L = np.linalg.cholesky(H_mm * sc[:, None] * sc[None, :])
        except np.linalg.LinAlgError:
            L = None
        if L is not None and np.min(np.diag(L)) ** 2 > _CHOLESKY_MIN_PIVOT2:
            X = scipy.linalg.solve_triangular(L, sc[:, None] * H[:m, m:], lower=True,
                                              check_finite=False)
            out = H[m:, m:] - X.T @ X
            return 0.5 * (out + out.T)
    n = H.shape[0]
    return marginalize_dense(H, np.zeros(n), np.arange(m, n), np.arange(m))[0]


def marginal_information(H: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Information (inverse marginal covariance) of the variables ``idx`` of a Gaussian with
    information matrix ``H``: all other variables are marginalised out."""
    idx = np.asarray(idx, dtype=np.int64)
    others = np.setdiff1d(np.arange(H.shape[0]), idx)
    return information_schur_complement(H, idx, others)


def log_det(info: np.ndarray) -> float:
    """``ln det(info)``, or ``-inf`` when ``info`` is not positive definite."""
    sign, value = np.linalg.slogdet(info)
    return float(value) if sign > 0 else float("-inf")


@dataclasses.dataclass(frozen=True)
class WindowHessian:
    """The linearised pose system of the window at one estimate.

    Pose ``frame_ids[k]`` owns rows ``6k:6k+6`` (twist ``[v, w]`` of the decoupled increment
    on ``T_w_c``, paper Eq. 14). ``H = H_reprojection + H_prior + H_scale_fix + H_no_motion``
    and likewise ``b`` (``b = J^T W r``, step ``-H^-1 b``); ``H_reprojection`` has the landmarks
    eliminated (Schur complement of their 3x3 blocks), ``H_reprojection_raw`` and
    ``b_reprojection_raw`` are the pose-pose block and pose gradient before that elimination.
    ``H_prior`` is the marginalisation prior including the gauge
    prior of the first pose. Units: information per pixel^2-weighted cost, poses in map units
    and radians.
    """

    frame_ids: tuple[int, ...]
    poses: np.ndarray  # (K,4,4) T_w_c at which the system was linearised
    H: np.ndarray
    b: np.ndarray
    H_reprojection: np.ndarray
    b_reprojection: np.ndarray
    H_reprojection_raw: np.ndarray
    b_reprojection_raw: np.ndarray
    H_prior: np.ndarray
    b_prior: np.ndarray
    H_scale_fix: np.ndarray
    H_no_motion: np.ndarray
    cost: float

    def index(self, frame_id: int) -> int:
        return self.frame_ids.index(frame_id)

    def block(self, frame_id: int) -> slice:
        """Row slice of a pose in ``H`` and ``b``."""
        k = self.index(frame_id)
        return slice(6 * k, 6 * k + 6)

    def pose_information(self, frame_id: int) -> np.ndarray:
        """6x6 marginal information of a pose (all other poses marginalised out of ``H``)."""
        k = self.index(frame_id)
        return marginal_information(self.H, np.arange(6 * k, 6 * k + 6))

    def negative_entropy(self, frame_id: int, include_translation: bool = True) -> float:
        """Negative entropy ``ln det I`` of paper Eq. 10 of a pose's marginal information.

        With ``include_translation=False`` the translation is marginalised out as well and the
        3x3 rotation information is used (reference: translation only when more than 5 finite
        points are connected). The value can be negative, and is ``-inf`` for a singular
        information matrix.
        """
        info = self.pose_information(frame_id)
        if not include_translation:
            info = marginal_information(info, np.arange(3, 6))
        return log_det(info)
