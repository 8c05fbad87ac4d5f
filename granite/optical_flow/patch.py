"""Numba kernels for one patch: bilinear sampling and the mean-normalised SE(2) template.

Images are pyramid levels inside a flat float32 buffer: pixel (x, y) of a level with offset
``off`` and width ``w`` is ``buf[off + y * w + x]``; pixel centres are at integer coordinates.

A patch samples the image at ``centre + R(theta) @ q_i`` for the pattern offsets ``q_i``. Its
intensities are divided by their mean (invariance to gain changes). The template (the patch
in the reference image, ``theta = 0``) stores the normalised intensities ``t``, the Jacobian
``J`` (P x 3) of the normalised intensities w.r.t. an SE(2) increment ``(tx, ty, theta)``
applied on the pattern side (including the change of the mean), ``(J^T J)^-1`` and ``J^T t``:
everything the inverse-compositional Gauss-Newton step needs; and the patch mean (for the
expected tracking precision, :mod:`granite.optical_flow.noise`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_EPS = 1e-9
#: LLVM fast-math flags: reassociation and contraction, but NaN/inf semantics kept so the
#: validity checks stay meaningful.
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
_FASTMATH = FASTMATH


@njit(cache=True, inline="always")
def _u(i):
    """An index into a pyramid buffer as unsigned: the callers keep their indices inside the
    buffer, and numba then leaves out its negative-index wraparound (a compare and select
    per load, a quarter of the instructions of the sampling loops)."""
    return np.uint64(i)


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def in_bounds(x: float, y: float, w: int, h: int, margin: float) -> bool:
    """True when (x, y) is at least ``margin`` pixels inside a w x h image."""
    return x >= margin and y >= margin and x <= w - 1 - margin and y <= h - 1 - margin


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def interp(buf, off, w, x, y):
    """Bilinear intensity at (x, y); the caller guarantees the 2x2 neighbourhood is inside."""
    ix = int(x)
    iy = int(y)
    dx = x - ix
    dy = y - iy
    i = off + iy * w + ix
    top = (1.0 - dx) * buf[_u(i)] + dx * buf[_u(i + 1)]
    bottom = (1.0 - dx) * buf[_u(i + w)] + dx * buf[_u(i + w + 1)]
    return (1.0 - dy) * top + dy * bottom


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def interp_grad(buf, off, w, x, y):
    """Bilinear intensity and its gradient (central differences of bilinear samples 1 px
    apart). Needs a 1 px margin beyond the 2x2 neighbourhood."""
    ix = int(x)
    iy = int(y)
    dx = x - ix
    dy = y - iy
    ddx = 1.0 - dx
    ddy = 1.0 - dy
    i = off + iy * w + ix
    p00 = buf[_u(i)]
    p10 = buf[_u(i + 1)]
    p01 = buf[_u(i + w)]
    p11 = buf[_u(i + w + 1)]
    value = ddx * ddy * p00 + dx * ddy * p10 + ddx * dy * p01 + dx * dy * p11
    # x - 1 and x + 1
    pm0 = buf[_u(i - 1)]
    pm1 = buf[_u(i + w - 1)]
    p20 = buf[_u(i + 2)]
    p21 = buf[_u(i + w + 2)]
    v_mx = ddx * ddy * pm0 + dx * ddy * p00 + ddx * dy * pm1 + dx * dy * p01
    v_px = ddx * ddy * p10 + dx * ddy * p20 + ddx * dy * p11 + dx * dy * p21
    # y - 1 and y + 1
    p0m = buf[_u(i - w)]
    p1m = buf[_u(i - w + 1)]
    p02 = buf[_u(i + 2 * w)]
    p12 = buf[_u(i + 2 * w + 1)]
    v_my = ddx * ddy * p0m + dx * ddy * p1m + ddx * dy * p00 + dx * dy * p10
    v_py = ddx * ddy * p01 + dx * ddy * p11 + ddx * dy * p02 + dx * dy * p12
    return value, 0.5 * (v_px - v_mx), 0.5 * (v_py - v_my)


#: Rows of a template's ``aux`` block as :func:`make_template` fills it.
AUX_ROWS = 5


@njit(cache=True)
def template_workspace(num_levels: int, num_samples: int):
    """Empty per-level template arrays of one point, ``(st, data, valid, jac, aux)``, in the
    shapes :func:`make_template` fills (``st`` marks a level's template as computed)."""
    return (np.empty(num_levels, dtype=np.int8),
            np.empty((num_levels, num_samples), dtype=np.float32),
            np.empty((num_levels, num_samples), dtype=np.bool_),
            np.empty((num_levels, num_samples, 3), dtype=np.float32),
            np.empty((num_levels, AUX_ROWS, 3), dtype=np.float32))


@njit(cache=True)
def pattern_radius(pattern) -> float:
    """Largest distance of a pattern sample from the patch centre (plus 1e-6)."""
    radius = 0.0
    for i in range(pattern.shape[0]):
        radius = max(radius, math.sqrt(pattern[i, 0] ** 2 + pattern[i, 1] ** 2))
    return radius + 1e-6


@njit(cache=True)
def unit_lattice_side(pattern) -> int:
    """``m`` when ``pattern`` is the m x m lattice of one-pixel spacing in the order of
    :func:`granite.optical_flow.patterns.grid_pattern` (rows from ``y = +r`` down, ``x``
    ascending, ``r = (m - 1) / 2``), exactly; else 0. Such a pattern's samples share their
    bilinear weights, which :func:`make_template_at` exploits."""
    n = pattern.shape[0]
    m = int(math.sqrt(n) + 0.5)
    if m < 2 or m * m != n:
        return 0
    r = 0.5 * (m - 1)
    for row in range(m):
        for col in range(m):
            i = row * m + col
            if pattern[i, 0] != col - r or pattern[i, 1] != r - row:
                return 0
    return m


@njit(cache=True)
def lattice_workspace(m: int):
    """Scratch rows of :func:`make_template_at` for an m x m unit lattice (zero size for
    m = 0: no lattice)."""
    k = m + 3 if m > 0 else 0
    return np.empty((2, k, k))


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def _sample_lattice(buf, off, w, cx, cy, m, pattern, data, valid, jac, pt, lv, ws):
    """The raw samples and gradients of :func:`_sample_pattern` for the m x m unit lattice
    (:func:`unit_lattice_side`) lying wholly inside the image: every sample has the same
    bilinear weights, so the (m + 2)^2 bilinear values around the lattice are interpolated
    separably (rows, then columns) and the gradients are their central differences, the same
    values as :func:`interp_grad` per sample. Returns (total, g0, g1, g2)."""
    r = 0.5 * (m - 1)
    xs = cx - r - 1.0
    ys = cy - r - 1.0
    ix = int(xs)
    iy = int(ys)
    dx = xs - ix
    dy = ys - iy
    ddx = 1.0 - dx
    ddy = 1.0 - dy
    k_max = m + 2
    rows = ws[0]
    vals = ws[1]
    # rows[j, k]: row iy + j interpolated at x = xs + k; vals[j, k]: bilinear at (xs + k, ys + j)
    for j in range(k_max + 1):
        base = off + (iy + j) * w + ix
        for k in range(k_max):
            rows[j, k] = ddx * buf[_u(base + k)] + dx * buf[_u(base + k + 1)]
    for j in range(k_max):
        for k in range(k_max):
            vals[j, k] = ddy * rows[j, k] + dy * rows[j + 1, k]
    total = 0.0
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for row in range(m):
        j = m - row  # sample row ``row`` is at y = cy + r - row = ys + (m - row)
        for col in range(m):
            k = col + 1
            i = row * m + col
            v = vals[j, k]
            gx = 0.5 * (vals[j, k + 1] - vals[j, k - 1])
            gy = 0.5 * (vals[j + 1, k] - vals[j - 1, k])
            gt = -pattern[i, 1] * gx + pattern[i, 0] * gy
            data[pt, lv, i] = v
            valid[pt, lv, i] = True
            jac[pt, lv, i, 0] = gx
            jac[pt, lv, i, 1] = gy
            jac[pt, lv, i, 2] = gt
            total += v
            g0 += gx
            g1 += gy
            g2 += gt
    return total, g0, g1, g2


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def _sample_pattern(buf, off, w, h, cx, cy, pattern, margin, data, valid, jac, pt, lv):
    """The raw samples of a template: intensity and gradient of each pattern sample inside
    the image (``valid``), zeros elsewhere. Returns (total, number valid, g0, g1, g2): the sums
    of the valid intensities and Jacobian columns."""
    n = pattern.shape[0]
    total = 0.0
    n_valid = 0
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for i in range(n):
        qx = pattern[i, 0]
        qy = pattern[i, 1]
        x = cx + qx
        y = cy + qy
        if in_bounds(x, y, w, h, margin):
            v, gx, gy = interp_grad(buf, off, w, x, y)
            gt = -qy * gx + qx * gy
            data[pt, lv, i] = v
            valid[pt, lv, i] = True
            total += v
            n_valid += 1
            jac[pt, lv, i, 0] = gx
            jac[pt, lv, i, 1] = gy
            jac[pt, lv, i, 2] = gt
            g0 += gx
            g1 += gy
            g2 += gt
        else:
            data[pt, lv, i] = 0.0
            valid[pt, lv, i] = False
            jac[pt, lv, i, 0] = 0.0
            jac[pt, lv, i, 1] = 0.0
            jac[pt, lv, i, 2] = 0.0
    return total, n_valid, g0, g1, g2


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def make_template_at(buf, off, w, h, cx, cy, pattern, margin, data, valid, jac, aux, pt, lv,
                     lattice, ws) -> int:
    """:func:`make_template` into point ``pt``, level ``lv`` of the template arrays of many
    points (``data`` (N, L, P), ``valid`` (N, L, P), ``jac`` (N, L, P, 3), ``aux``
    (N, L, 5, 3)), the tracker's caches, without making views of them (a view costs two
    atomic reference-count updates: 5 % of the tracking time). ``lattice``:
    :func:`unit_lattice_side` of ``pattern``, and ``ws`` its :func:`lattice_workspace`; a
    lattice wholly inside the image is sampled separably (the same values as sample by sample
    up to the last bits, in about half the time)."""
    n = pattern.shape[0]
    if not in_bounds(cx, cy, w, h, margin):
        # The tracker rejects such centres anyway; for a point-symmetric pattern without
        # samples on the axes (like the 52-point one) at most half the samples are inside.
        return 0
    half = 0.5 * (lattice - 1)  # the lattice's half-width
    if lattice > 0 and in_bounds(cx - half, cy - half, w, h, margin) and in_bounds(cx + half, cy + half, w, h, margin):
        total, g0, g1, g2 = _sample_lattice(buf, off, w, cx, cy, lattice, pattern, data, valid, jac, pt, lv, ws)
        n_valid = n
    else:
        total, n_valid, g0, g1, g2 = _sample_pattern(buf, off, w, h, cx, cy, pattern, margin, data, valid,
                                                     jac, pt, lv)
    if 2 * n_valid <= n or total <= _EPS:
        return 0
    mean_inv = n_valid / total
    # d(v_i / mean)/d xi = (g_i - v_i * sum_j g_j / total) / mean
    h00 = h01 = h02 = h11 = h12 = h22 = 0.0
    jt0 = jt1 = jt2 = 0.0
    for i in range(n):
        if valid[pt, lv, i]:
            r = data[pt, lv, i] / total
            j0 = (jac[pt, lv, i, 0] - g0 * r) * mean_inv
            j1 = (jac[pt, lv, i, 1] - g1 * r) * mean_inv
            j2 = (jac[pt, lv, i, 2] - g2 * r) * mean_inv
            t = data[pt, lv, i] * mean_inv
            jac[pt, lv, i, 0] = j0
            jac[pt, lv, i, 1] = j1
            jac[pt, lv, i, 2] = j2
            data[pt, lv, i] = t
            jt0 += j0 * t
            jt1 += j1 * t
            jt2 += j2 * t
            h00 += j0 * j0
            h01 += j0 * j1
            h02 += j0 * j2
            h11 += j1 * j1
            h12 += j1 * j2
            h22 += j2 * j2
    # Inverse of the symmetric 3x3 normal matrix by cofactors.
    c00 = h11 * h22 - h12 * h12
    c01 = h02 * h12 - h01 * h22
    c02 = h01 * h12 - h02 * h11
    c11 = h00 * h22 - h02 * h02
    c12 = h01 * h02 - h00 * h12
    c22 = h00 * h11 - h01 * h01
    det = h00 * c00 + h01 * c01 + h02 * c02
    scale = h00 * h11 * h22
    if not (scale > 1e-30) or not (det > 1e-9 * scale):
        return 0
    inv = 1.0 / det
    aux[pt, lv, 0, 0] = c00 * inv
    aux[pt, lv, 0, 1] = c01 * inv
    aux[pt, lv, 0, 2] = c02 * inv
    aux[pt, lv, 1, 0] = c01 * inv
    aux[pt, lv, 1, 1] = c11 * inv
    aux[pt, lv, 1, 2] = c12 * inv
    aux[pt, lv, 2, 0] = c02 * inv
    aux[pt, lv, 2, 1] = c12 * inv
    aux[pt, lv, 2, 2] = c22 * inv
    aux[pt, lv, 3, 0] = jt0
    aux[pt, lv, 3, 1] = jt1
    aux[pt, lv, 3, 2] = jt2
    aux[pt, lv, 4, 0] = total / n_valid
    aux[pt, lv, 4, 1] = 0.0
    aux[pt, lv, 4, 2] = 0.0
    return 2 if n_valid == n else 1


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def make_template(buf, off, w, h, cx, cy, pattern, margin, data, valid, jac, aux) -> int:
    """Fill the template of the patch centred at (cx, cy) (level pixels).

    Outputs (preallocated float32 except ``valid``): ``data`` (P,) normalised intensities
    ``t``, ``valid`` (P,) bool, ``jac`` (P, 3) Jacobian ``J`` of the normalised intensities,
    ``aux`` (5, 3): rows 0-2 ``(J^T J)^-1``, row 3 ``J^T t``, ``aux[4, 0]`` the patch mean
    (input intensity units; ``aux[4, 1:]`` zero). Returns 0 (invalid) when the
    centre or at least half of the pattern is not inside the image, the patch mean is not
    positive, or ``J^T J`` is singular (a textureless patch); 2 when every sample is valid,
    else 1.
    """
    lattice = unit_lattice_side(pattern)
    return make_template_at(buf, off, w, h, cx, cy, pattern, margin,
                            data.reshape((1, 1) + data.shape), valid.reshape((1, 1) + valid.shape),
                            jac.reshape((1, 1) + jac.shape), aux.reshape((1, 1) + aux.shape), 0, 0,
                            lattice, lattice_workspace(lattice))


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def patch_increment(buf, off, w, h, tx, ty, cos_t, sin_t, pattern, radius, margin, state, data, valid, jac, aux, pt, lv):
    """Gauss-Newton step of the patch warped to (tx, ty, theta) against its template.

    ``state`` and point ``pt``, level ``lv`` of ``data``, ``valid``, ``jac``, ``aux`` are the
    template (see :func:`make_template_at`); ``radius`` bounds the pattern's sample distance from the centre.
    Returns (ok, d0, d1, d2) with the increment ``-(J^T J)^-1 J^T r`` over the samples
    inside the image and valid in the template, ``r_i = v_i * sum(t) / sum(v) - t_i`` (the
    current intensities scaled to the template's normalised sum). ``ok`` is False when at
    most half of the pattern has a residual or the patch mean is not positive.
    """
    n = pattern.shape[0]
    total = 0.0
    b0 = 0.0
    b1 = 0.0
    b2 = 0.0
    # J^T r = norm * J^T v - J^T t with norm = sum(t) / sum(v); sum(t) = n for a full patch.
    if state == 2 and in_bounds(tx, ty, w, h, margin + radius):
        # Fast path: every sample inside the image and valid in the template.
        for i in range(n):
            qx = pattern[i, 0]
            qy = pattern[i, 1]
            v = interp(buf, off, w, cos_t * qx - sin_t * qy + tx, sin_t * qx + cos_t * qy + ty)
            total += v
            b0 += jac[pt, lv, i, 0] * v
            b1 += jac[pt, lv, i, 1] * v
            b2 += jac[pt, lv, i, 2] * v
        sum_t = float(n)  # normalised template intensities have mean 1
        n_res = n
        t0 = aux[pt, lv, 3, 0]
        t1 = aux[pt, lv, 3, 1]
        t2 = aux[pt, lv, 3, 2]
    else:
        # Samples outside the image or invalid in the template are dropped; the current
        # samples are scaled to the template's normalised sum over the remaining ones.
        n_res = 0
        sum_t = 0.0
        t0 = 0.0
        t1 = 0.0
        t2 = 0.0
        for i in range(n):
            if not valid[pt, lv, i]:
                continue
            qx = pattern[i, 0]
            qy = pattern[i, 1]
            x = cos_t * qx - sin_t * qy + tx
            y = sin_t * qx + cos_t * qy + ty
            if in_bounds(x, y, w, h, margin):
                v = interp(buf, off, w, x, y)
                j0 = jac[pt, lv, i, 0]
                j1 = jac[pt, lv, i, 1]
                j2 = jac[pt, lv, i, 2]
                d = data[pt, lv, i]
                total += v
                sum_t += d
                b0 += j0 * v
                b1 += j1 * v
                b2 += j2 * v
                t0 += j0 * d
                t1 += j1 * d
                t2 += j2 * d
                n_res += 1
    if 2 * n_res <= n or total <= _EPS:
        return False, 0.0, 0.0, 0.0
    norm = sum_t / total
    r0 = norm * b0 - t0
    r1 = norm * b1 - t1
    r2 = norm * b2 - t2
    d0 = -(aux[pt, lv, 0, 0] * r0 + aux[pt, lv, 0, 1] * r1 + aux[pt, lv, 0, 2] * r2)
    d1 = -(aux[pt, lv, 1, 0] * r0 + aux[pt, lv, 1, 1] * r1 + aux[pt, lv, 1, 2] * r2)
    d2 = -(aux[pt, lv, 2, 0] * r0 + aux[pt, lv, 2, 1] * r1 + aux[pt, lv, 2, 2] * r2)
    return True, d0, d1, d2


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def patch_zncc(buf, off, w, h, tx, ty, theta, pattern, margin, data, valid) -> float:
    """Zero-mean normalised cross-correlation of the patch warped to (tx, ty, theta) (level
    pixels) with its template (``data``, ``valid`` from :func:`make_template`), over the
    samples inside the image and valid in the template; -1 when fewer than half of the
    pattern are usable or either side has no variance."""
    n = pattern.shape[0]
    c = math.cos(theta)
    s = math.sin(theta)
    m = 0
    st = 0.0
    sv = 0.0
    stt = 0.0
    svv = 0.0
    stv = 0.0
    for i in range(n):
        if not valid[i]:
            continue
        qx = pattern[i, 0]
        qy = pattern[i, 1]
        x = c * qx - s * qy + tx
        y = s * qx + c * qy + ty
        if not in_bounds(x, y, w, h, margin):
            continue
        v = interp(buf, off, w, x, y)
        t = data[i]
        m += 1
        st += t
        sv += v
        stt += t * t
        svv += v * v
        stv += t * v
    if 2 * m <= n:
        return -1.0
    return _correlation(m, st, sv, stt, svv, stv)


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def patch_zncc_at(buf, off, w, h, tx, ty, theta, pattern, radius, margin, state, data, valid, pt, lv) -> float:
    """:func:`patch_zncc` against the template of point ``pt``, level ``lv`` of the template
    arrays of many points (``data`` (N, L, P), ``valid`` (N, L, P); ``state`` its
    :func:`make_template_at` value), read without making views of them. A complete template
    (``state == 2``) whose warped pattern lies wholly inside the image (``radius`` bounds the
    samples' distance from the centre) takes a branch-free loop over all samples (the same
    sums in another order: vectorised)."""
    n = pattern.shape[0]
    if not (state == 2 and in_bounds(tx, ty, w, h, margin + radius)):
        return patch_zncc(buf, off, w, h, tx, ty, theta, pattern, margin, data[pt, lv], valid[pt, lv])
    c = math.cos(theta)
    s = math.sin(theta)
    st = 0.0
    sv = 0.0
    stt = 0.0
    svv = 0.0
    stv = 0.0
    for i in range(n):
        qx = pattern[i, 0]
        qy = pattern[i, 1]
        v = interp(buf, off, w, c * qx - s * qy + tx, s * qx + c * qy + ty)
        t = data[pt, lv, i]
        st += t
        sv += v
        stt += t * t
        svv += v * v
        stv += t * v
    return _correlation(n, st, sv, stt, svv, stv)


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy", inline="always")
def _correlation(m, st, sv, stt, svv, stv):
    """The correlation coefficient of ``m`` pairs (t, v) from their sums (``st`` = sum t,
    ``stt`` = sum t*t, ``stv`` = sum t*v, ...); -1 when either side has no variance."""
    vt = stt - st * st / m
    vv = svv - sv * sv / m
    if not (vt > 1e-12 and vv > 1e-12):
        return -1.0
    return (stv - st * sv / m) / math.sqrt(vt * vv)
