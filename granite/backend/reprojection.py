"""Reprojection residuals and Jacobians (paper Eq. 5-7), vectorised with numba.

For an observation ``z`` of landmark ``(b(s), d)`` hosted by frame ``h`` and seen in frame
``t``, with camera poses ``T_w_h`` and ``T_w_t`` (camera-to-world)::

    q   = R_w_h b + (t_w_h - t_w_t) d      (world-oriented, up to the positive scale 1/d)
    p_t = R_w_t^T q = R_t_h b + t_t_h d    (point in the target camera frame)
    r   = pi(p_t) - z                       (pixels)

Pose increments are the decoupled left increment of paper Eq. 14 on ``T_w_c``
(``R <- exp([w]_x) R``, ``t <- t + v``, twist ``[v, w]``), which gives

    dp_t/dv_h =  d R_w_t^T          dp_t/dw_h = -R_w_t^T [R_w_h b]_x
    dp_t/dv_t = -d R_w_t^T          dp_t/dw_t =  R_w_t^T [q]_x
    dp_t/ds   =  R_t_h db/ds        dp_t/dd   =  t_t_h

Since ``[q]_x = [R_w_h b]_x + d [t_w_h - t_w_t]_x``, the target's Jacobian is the host's
times ``M = [[-I, [t_w_h - t_w_t]_x], [0, -I]]``: only ``J_h`` is written, and the backend
works with the relative increment ``dx_h + M dx_t`` (:func:`granite.backend.schur.schur_reduce`).

Observations in the host frame itself give ``p_t = b`` and constrain the bearing only.
For a point at infinity (``d == 0``) the column ``dp_t/dd`` is set to zero (as in the
reference): such a point constrains rotations only and keeps ``d = 0`` until the frontend
re-triangulates it; a finite point whose ``d`` is clamped to 0 joins them.
All Jacobians (including ``dpi/dp``) are evaluated at the poses passed as ``poses_lin``
(first-estimate Jacobians: the linearisation point for states in the marginalisation prior, the
current estimate for the others, as in Basalt); residuals are evaluated at ``poses``. This keeps
the 7-dimensional monocular gauge out of the information of the prior.

The projection ``pi`` and ``dpi/dp`` come from the camera model's per-point kernel
(:func:`granite.camera.batch.project_point`), inlined into one pass over the observations that
transforms, projects and linearises each (:func:`linearize_fused`).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import types
from numba.extending import overload

from granite.backend.packing import PackedObservations
from granite.camera import batch
from granite.camera.batch import DS, KB4, PINHOLE
from granite.backend.stereographic import bearing_from_stereo_into


@numba.njit(cache=True, nogil=True)
def transform_observations(poses: np.ndarray, lm_host: np.ndarray, lm_s: np.ndarray,
                           lm_d: np.ndarray, obs_lm: np.ndarray, obs_tgt: np.ndarray
                           ) -> np.ndarray:
    """Points ``p_t`` (N,3) in the observing frames at ``poses`` (the bearing itself for
    observations in the host)."""
    n = obs_lm.shape[0]
    p = np.empty((n, 3))
    b = np.empty(3)
    Jb = np.empty((3, 2))
    for k in range(n):
        i = obs_lm[k]
        h = lm_host[i]
        t = obs_tgt[k]
        bearing_from_stereo_into(lm_s[i, 0], lm_s[i, 1], b, Jb)
        if h == t:
            for r in range(3):
                p[k, r] = b[r]
        else:
            _point_in_target(poses[h], poses[t], b, lm_d[i], p, k)
    return p


@numba.njit(cache=True, nogil=True)
def _point_in_target(T_h: np.ndarray, T_t: np.ndarray, b: np.ndarray, d: float,
                     out: np.ndarray, k: int) -> None:
    """``out[k] = R_w_t^T (R_w_h b + (t_w_h - t_w_t) d)``."""
    q0 = T_h[0, 0] * b[0] + T_h[0, 1] * b[1] + T_h[0, 2] * b[2] + (T_h[0, 3] - T_t[0, 3]) * d
    q1 = T_h[1, 0] * b[0] + T_h[1, 1] * b[1] + T_h[1, 2] * b[2] + (T_h[1, 3] - T_t[1, 3]) * d
    q2 = T_h[2, 0] * b[0] + T_h[2, 1] * b[1] + T_h[2, 2] * b[2] + (T_h[2, 3] - T_t[2, 3]) * d
    for r in range(3):
        out[k, r] = T_t[0, r] * q0 + T_t[1, r] * q1 + T_t[2, r] * q2


@numba.njit(cache=True, nogil=True)
def _obs_weight(level: int, d: float, inv_var: float, inf_factor: float) -> float:
    w = inv_var / (2.0 ** level)
    if d == 0.0:
        w *= inf_factor
    return w


@numba.njit(cache=True, nogil=True, inline="always")
def _store_residual(k: int, u: float, v: float, obs_uv: np.ndarray, obs_level: np.ndarray,
                    d: float, inv_var: float, huber: float, inf_factor: float, r: np.ndarray,
                    w: np.ndarray) -> float:
    """Residual ``r[k]`` and robust weight ``w[k]`` of observation ``k`` projected at
    ``(u, v)``; returns its robust cost ``(2 - h) h w0 |r|^2`` (Huber ``h``)."""
    r0 = u - obs_uv[k, 0]
    r1 = v - obs_uv[k, 1]
    e = math.sqrt(r0 * r0 + r1 * r1)
    hw = 1.0 if e < huber else huber / e
    w0 = _obs_weight(obs_level[k], d, inv_var, inf_factor)
    w[k] = hw * w0
    r[k, 0] = r0
    r[k, 1] = r1
    return (2.0 - hw) * hw * w0 * e * e


def _linearize_fused(model, kp, poses, poses_lin, same_lin, lm_host, lm_s, lm_d, obs_lm,
                     obs_tgt, obs_uv, obs_level, inv_var, huber, inf_factor, r, w, J_h, J_l,
                     valid):
    """Typing stub of :func:`linearize_fused`'s loop for one camera model (njit only)."""
    raise NotImplementedError


@overload(_linearize_fused, prefer_literal=True, jit_options={"cache": True})
def _linearize_fused_loop(model, kp, poses, poses_lin, same_lin, lm_host, lm_s, lm_d, obs_lm,
                          obs_tgt, obs_uv, obs_level, inv_var, huber, inf_factor, r, w, J_h,
                          J_l, valid):
    """The loop specialised on the camera model (its per-point projection inlined)."""
    if not isinstance(model, types.IntegerLiteral):
        return None
    model_id = model.literal_value
    nk = batch.num_intrinsics(model_id)

    def loop(model, kp, poses, poses_lin, same_lin, lm_host, lm_s, lm_d, obs_lm, obs_tgt,
             obs_uv, obs_level, inv_var, huber, inf_factor, r, w, J_h, J_l, valid):
        # one observation's intermediates (row 0): point at the estimate and at the
        # linearisation point, its pixels, d pixel / d point, 3-D Jacobians
        p = np.empty((1, 3))
        p_lin = np.empty((1, 3))
        uv = np.empty((1, 2))
        uv_res = np.empty((1, 2))
        J_pi = np.empty((1, 2, 3))
        J_k = np.empty((1, 2, nk))
        no_jp = np.empty((0, 2, 3))
        no_jk = np.empty((0, 2, nk))
        J_h3 = np.empty((3, 6))
        J_l3 = np.empty((3, 3))
        rb = np.empty(3)
        b = np.empty(3)
        Jb = np.empty((3, 2))
        cost = 0.0
        for k in range(obs_lm.shape[0]):
            i = obs_lm[k]
            h = lm_host[i]
            t = obs_tgt[k]
            d = lm_d[i]
            bearing_from_stereo_into(lm_s[i, 0], lm_s[i, 1], b, Jb)
            if h == t:
                for c in range(3):
                    p[0, c] = b[c]
                    p_lin[0, c] = b[c]
                    J_l3[c, 0] = Jb[c, 0]
                    J_l3[c, 1] = Jb[c, 1]
                    J_l3[c, 2] = 0.0
                    for c2 in range(6):
                        J_h3[c, c2] = 0.0
            else:
                _point_in_target(poses[h], poses[t], b, d, p, 0)
                Th = poses_lin[h]
                Tt = poses_lin[t]
                _point_in_target(Th, Tt, b, d, p_lin, 0)
                for c in range(3):
                    rb[c] = Th[c, 0] * b[0] + Th[c, 1] * b[1] + Th[c, 2] * b[2]
                for c in range(3):
                    # row c of R_w_t^T is column c of R_w_t
                    a0 = Tt[0, c]
                    a1 = Tt[1, c]
                    a2 = Tt[2, c]
                    # landmark: dp/ds = R_t_h db/ds, dp/dd = t_t_h = R_w_t^T (t_w_h - t_w_t)
                    for c2 in range(2):
                        acc = 0.0
                        for m in range(3):
                            acc += (a0 * Th[0, m] + a1 * Th[1, m] + a2 * Th[2, m]) * Jb[m, c2]
                        J_l3[c, c2] = acc
                    if d == 0.0:
                        # points at infinity stay there: no inverse-distance update (as the
                        # reference)
                        J_l3[c, 2] = 0.0
                    else:
                        J_l3[c, 2] = (a0 * (Th[0, 3] - Tt[0, 3]) + a1 * (Th[1, 3] - Tt[1, 3])
                                      + a2 * (Th[2, 3] - Tt[2, 3]))
                    J_h3[c, 0] = d * a0
                    J_h3[c, 1] = d * a1
                    J_h3[c, 2] = d * a2
                    # a^T [x]_x = (a x x)^T = [a1 x2 - a2 x1, a2 x0 - a0 x2, a0 x1 - a1 x0]
                    J_h3[c, 3] = -(a1 * rb[2] - a2 * rb[1])
                    J_h3[c, 4] = -(a2 * rb[0] - a0 * rb[2])
                    J_h3[c, 5] = -(a0 * rb[1] - a1 * rb[0])
            ok = batch.project_point(model_id, kp, p_lin, 0, uv, J_pi, J_k, True)
            if not same_lin:  # residual at the estimate, Jacobians at the linearisation point
                ok = batch.project_point(model_id, kp, p, 0, uv_res, no_jp, no_jk,
                                         False) and ok
                uv[0, 0] = uv_res[0, 0]
                uv[0, 1] = uv_res[0, 1]
            valid[k] = ok
            if not ok:
                w[k] = 0.0
                r[k, 0] = 0.0
                r[k, 1] = 0.0
                for a in range(2):
                    for c in range(6):
                        J_h[k, a, c] = 0.0
                    for c in range(3):
                        J_l[k, a, c] = 0.0
                continue
            cost += _store_residual(k, uv[0, 0], uv[0, 1], obs_uv, obs_level, d, inv_var, huber,
                                    inf_factor, r, w)
            for a in range(2):
                for c in range(6):
                    sh = 0.0
                    for m in range(3):
                        sh += J_pi[0, a, m] * J_h3[m, c]
                    J_h[k, a, c] = sh
                for c in range(3):
                    sl = 0.0
                    for m in range(3):
                        sl += J_pi[0, a, m] * J_l3[m, c]
                    J_l[k, a, c] = sl
        return cost

    return loop


@numba.njit(cache=True, nogil=True)
def linearize_fused(model: int, kp: np.ndarray, poses: np.ndarray, poses_lin: np.ndarray,
                    same_lin: bool, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv, obs_level,
                    inv_var: float, huber: float, inf_factor: float, r, w, J_h, J_l,
                    valid) -> float:
    """Every observation transformed, projected and linearised in one pass.

    Writes residuals ``r`` (N,2) at ``poses``, robust information weights ``w`` (N,) (0 for
    invalid projections), pixel Jacobians w.r.t. the host twist and the landmark (N,2,6),
    (N,2,3) at ``poses_lin`` (the target twist's is ``J_h M``, ``M`` of
    :func:`granite.backend.schur.relative_map`: not written) (``same_lin``: the two are equal and
    one projection per observation serves both), the validity ``valid`` (N,), and returns the
    robust cost ``sum (2 - h) h w0 |r|^2`` (Huber: ``h = min(1, k/|r|)``, so ``w0 |r|^2``
    inside and ``w0 (2 k |r| - k^2)`` outside the threshold ``k``). Invalid projections get
    zero residuals and Jacobians. ``(model, kp)``: the camera's kernel id and parameters."""
    if model == KB4:
        return _linearize_fused(KB4, kp, poses, poses_lin, same_lin, lm_host, lm_s, lm_d,
                                obs_lm, obs_tgt, obs_uv, obs_level, inv_var, huber, inf_factor,
                                r, w, J_h, J_l, valid)
    if model == DS:
        return _linearize_fused(DS, kp, poses, poses_lin, same_lin, lm_host, lm_s, lm_d,
                                obs_lm, obs_tgt, obs_uv, obs_level, inv_var, huber, inf_factor,
                                r, w, J_h, J_l, valid)
    return _linearize_fused(PINHOLE, kp, poses, poses_lin, same_lin, lm_host, lm_s, lm_d,
                            obs_lm, obs_tgt, obs_uv, obs_level, inv_var, huber, inf_factor,
                            r, w, J_h, J_l, valid)


def _residuals_fused(model, kp, poses, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv,
                     obs_level, inv_var, huber, inf_factor, r, w, valid):
    """Typing stub of :func:`residuals_fused`'s loop for one camera model (njit only)."""
    raise NotImplementedError


@overload(_residuals_fused, prefer_literal=True, jit_options={"cache": True})
def _residuals_fused_loop(model, kp, poses, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv,
                          obs_level, inv_var, huber, inf_factor, r, w, valid):
    """The loop specialised on the camera model (its per-point projection inlined)."""
    if not isinstance(model, types.IntegerLiteral):
        return None
    model_id = model.literal_value
    nk = batch.num_intrinsics(model_id)

    def loop(model, kp, poses, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv, obs_level,
             inv_var, huber, inf_factor, r, w, valid):
        p = np.empty((1, 3))
        uv = np.empty((1, 2))
        no_jp = np.empty((0, 2, 3))
        no_jk = np.empty((0, 2, nk))
        b = np.empty(3)
        Jb = np.empty((3, 2))
        cost = 0.0
        for k in range(obs_lm.shape[0]):
            i = obs_lm[k]
            h = lm_host[i]
            t = obs_tgt[k]
            d = lm_d[i]
            bearing_from_stereo_into(lm_s[i, 0], lm_s[i, 1], b, Jb)
            if h == t:
                for c in range(3):
                    p[0, c] = b[c]
            else:
                _point_in_target(poses[h], poses[t], b, d, p, 0)
            ok = batch.project_point(model_id, kp, p, 0, uv, no_jp, no_jk, False)
            valid[k] = ok
            if not ok:
                w[k] = 0.0
                r[k, 0] = 0.0
                r[k, 1] = 0.0
                continue
            cost += _store_residual(k, uv[0, 0], uv[0, 1], obs_uv, obs_level, d, inv_var, huber,
                                    inf_factor, r, w)
        return cost

    return loop


@numba.njit(cache=True, nogil=True)
def residuals_fused(model: int, kp: np.ndarray, poses: np.ndarray, lm_host, lm_s, lm_d,
                    obs_lm, obs_tgt, obs_uv, obs_level, inv_var: float, huber: float,
                    inf_factor: float, r, w, valid) -> float:
    """The residuals ``r`` (N,2), robust weights ``w`` (N,), validity ``valid`` (N,) and robust
    cost of :func:`linearize_fused` at ``poses``, without Jacobians (the same values, by the
    same arithmetic, as its residual at the estimate)."""
    if model == KB4:
        return _residuals_fused(KB4, kp, poses, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv,
                                obs_level, inv_var, huber, inf_factor, r, w, valid)
    if model == DS:
        return _residuals_fused(DS, kp, poses, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv,
                                obs_level, inv_var, huber, inf_factor, r, w, valid)
    return _residuals_fused(PINHOLE, kp, poses, lm_host, lm_s, lm_d, obs_lm, obs_tgt, obs_uv,
                            obs_level, inv_var, huber, inf_factor, r, w, valid)


@numba.njit(cache=True, nogil=True)
def robust_cost(uv: np.ndarray, valid: np.ndarray, obs_uv: np.ndarray, obs_level: np.ndarray,
                obs_lm: np.ndarray, lm_d: np.ndarray, inv_var: float, huber: float,
                inf_factor: float) -> float:
    """The robust reprojection cost of :func:`linearize_fused` without Jacobians."""
    cost = 0.0
    for k in range(obs_lm.shape[0]):
        if not valid[k]:
            continue
        r0 = uv[k, 0] - obs_uv[k, 0]
        r1 = uv[k, 1] - obs_uv[k, 1]
        e = math.sqrt(r0 * r0 + r1 * r1)
        hw = 1.0 if e < huber else huber / e
        cost += (2.0 - hw) * hw * _obs_weight(obs_level[k], lm_d[obs_lm[k]], inv_var,
                                         inf_factor) * e * e
    return cost


class Workspace:
    """Preallocated per-observation outputs of the linearisation, reused across iterations of
    one problem (large temporary arrays would otherwise be page-faulted in on every
    iteration). ``view(n)`` gives a workspace for ``n <= capacity`` observations on the same
    memory (the window keeps one workspace for all its problems, so that the pages stay mapped
    across calls)."""

    _FIELDS = (("r", (2,)), ("w", ()), ("J_h", (2, 6)), ("J_l", (2, 3)))

    def __init__(self, n: int):
        self.capacity = int(n)
        for name, shape in self._FIELDS:
            setattr(self, name, np.empty((self.capacity,) + shape))

    def view(self, n: int) -> Workspace:
        """A workspace of ``n`` observations sharing this one's memory (C-contiguous)."""
        if n > self.capacity:
            raise ValueError(f"workspace of capacity {self.capacity} cannot hold {n}")
        ws = object.__new__(Workspace)
        ws.capacity = int(n)
        for name, _ in self._FIELDS:
            setattr(ws, name, getattr(self, name)[:n])
        return ws


class LinearizedObservations:
    """Residuals, weights and pixel Jacobians of a packed problem at one estimate: ``r``
    (N,2), ``w`` (N,), ``J_h`` (N,2,6) w.r.t. the host's twist, ``J_l`` (N,2,3) w.r.t. the
    landmark, and ``t_lin`` (K,3), the camera centres at the linearisation points: the
    Jacobian w.r.t. the target's twist is ``J_h M`` (:func:`granite.backend.schur.relative_map`
    of ``t_lin[h]``, ``t_lin[t]``)."""

    __slots__ = ("r", "w", "J_h", "J_l", "t_lin", "cost", "valid")

    def __init__(self, r, w, J_h, J_l, t_lin, cost, valid):
        self.r = r
        self.w = w
        self.J_h = J_h
        self.J_l = J_l
        self.t_lin = t_lin
        self.cost = float(cost)
        self.valid = valid


def linearize(camera, packed: PackedObservations, poses: np.ndarray, poses_lin: np.ndarray,
              inv_var: float, huber: float, inf_factor: float,
              workspace: Workspace | None = None) -> LinearizedObservations:
    """Linearise all observations of ``packed`` at ``poses`` (N,4,4) (``T_w_c`` per pose index),
    with pose Jacobians at ``poses_lin``. The returned arrays live in ``workspace`` (if given)
    and are overwritten by the next call with the same workspace."""
    ws = workspace if workspace is not None else Workspace(packed.num_observations)
    same_lin = poses_lin is poses or bool(np.array_equal(poses_lin, poses))
    valid = np.empty(packed.num_observations, dtype=np.bool_)
    cost = linearize_fused(camera.kernel_model, camera.kernel_params, poses, poses_lin,
                           same_lin, packed.lm_host, packed.lm_s, packed.lm_d, packed.obs_lm,
                           packed.obs_tgt, packed.obs_uv, packed.obs_level, inv_var, huber,
                           inf_factor, ws.r, ws.w, ws.J_h, ws.J_l, valid)
    t_lin = np.ascontiguousarray(poses_lin[:, :3, 3])
    return LinearizedObservations(ws.r, ws.w, ws.J_h, ws.J_l, t_lin, cost, valid)


def residuals_at(camera, packed: PackedObservations, poses: np.ndarray, inv_var: float,
                 huber: float, inf_factor: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Residuals ``r`` (N,2), robust weights ``w`` (N,), validity (N,) and robust cost at
    ``poses`` and the landmark states of ``packed``: what :func:`linearize` gives at the
    estimate, without Jacobians (:func:`residuals_fused`)."""
    n = packed.num_observations
    r = np.empty((n, 2))
    w = np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    cost = residuals_fused(camera.kernel_model, camera.kernel_params, poses, packed.lm_host,
                           packed.lm_s, packed.lm_d, packed.obs_lm, packed.obs_tgt,
                           packed.obs_uv, packed.obs_level, inv_var, huber, inf_factor, r, w,
                           valid)
    return r, w, valid, float(cost)


def reprojection_residuals(camera, packed: PackedObservations, poses: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals ``pi(p_t) - z`` (N,2) and validity (N,) at ``poses`` (no weighting)."""
    p = transform_observations(poses, packed.lm_host, packed.lm_s, packed.lm_d, packed.obs_lm,
                               packed.obs_tgt)
    uv, valid = camera.project(p)
    return np.asarray(uv) - packed.obs_uv, np.asarray(valid, dtype=bool)


def reprojection_cost(camera, packed: PackedObservations, poses: np.ndarray, inv_var: float,
                      huber: float, inf_factor: float) -> float:
    """Robust reprojection cost at ``poses`` and the landmark states of ``packed``."""
    p = transform_observations(poses, packed.lm_host, packed.lm_s, packed.lm_d, packed.obs_lm,
                               packed.obs_tgt)
    uv, valid = camera.project(p)
    return float(robust_cost(np.ascontiguousarray(uv, dtype=np.float64),
                             np.ascontiguousarray(valid, dtype=np.bool_), packed.obs_uv,
                             packed.obs_level, packed.obs_lm, packed.lm_d, inv_var, huber,
                             inf_factor))
