"""Numba kernels: coarse-to-fine patch tracking with a forward-backward check.

A point is a patch centre in level-0 pixels; at level ``l`` it is at ``p / 2**l``. A patch
created at level ``c`` is tracked from the coarsest level down to ``c``: at each level the
template is sampled around the point's position in the reference image, and an SE(2) warp
(translation in level pixels, rotation angle) is refined by up to ``iterations``
inverse-compositional Gauss-Newton steps, ``W <- W o exp(-(J^T J)^-1 J^T r)``. Levels coarser than
``c + 1`` where the patch does not fit into the image are skipped (small images have tiny
coarse levels); a failure at level ``c + 1`` or ``c`` rejects the track.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from granite.optical_flow.patch import FASTMATH as _FASTMATH
from granite.optical_flow.noise import translation_lambda_max
from granite.optical_flow.local_flow import local_guesses
from granite.optical_flow.work_share import PointShare, fetch_add
from granite.optical_flow.patch import (
    AUX_ROWS,
    in_bounds,
    lattice_workspace,
    make_template_at,
    patch_increment,
    patch_zncc_at,
    pattern_radius,
    unit_lattice_side,
)

#: Gauss-Newton stops early once a step is below 0.01 pixels on the creation level of a patch
#: and below 0.1 pixels on coarser levels, which only need to start the next level well
#: inside its convergence basin (this saves ~40 % of the iterations at equal accuracy).
_MIN_STEP_SQ = 0.01**2
_MIN_STEP_SQ_COARSE = 0.1**2


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def track_level(
    buf, off, w, h, tx, ty, theta, pattern, radius, margin, iterations, min_step_sq, state, data, valid, jac, aux,
    pt, lv,
):
    """Refine the warp (tx, ty, theta) (level pixels) of one template (point ``pt``, level
    ``lv`` of the template arrays, see :func:`granite.optical_flow.patch.make_template_at`).
    Returns (ok, tx, ty, theta).

    Stops early once a step moves the patch by less than ``sqrt(min_step_sq)`` level pixels
    (translation plus rotation times a 5 px lever arm).
    """
    c = math.cos(theta)
    s = math.sin(theta)
    for _ in range(iterations):
        ok, d0, d1, d2 = patch_increment(
            buf, off, w, h, tx, ty, c, s, pattern, radius, margin, state, data, valid, jac, aux, pt, lv
        )
        if not ok:
            return False, tx, ty, theta
        # SE(2) exponential of (d0, d1, d2), composed on the right: W <- W o exp(d).
        if abs(d2) < 0.05:  # series, truncation error < 1e-10
            q = d2 * d2
            a = 1.0 - q / 6.0 + q * q / 120.0  # sin(d2) / d2
            b = d2 * (0.5 - q / 24.0 + q * q / 720.0)  # (1 - cos(d2)) / d2
            cd = 1.0 - q * (0.5 - q / 24.0)
            sd = d2 * a
        else:
            sd = math.sin(d2)
            cd = math.cos(d2)
            a = sd / d2
            b = (1.0 - cd) / d2
        ex = a * d0 - b * d1
        ey = b * d0 + a * d1
        tx += c * ex - s * ey
        ty += s * ex + c * ey
        c, s = c * cd - s * sd, s * cd + c * sd
        theta += d2
        if not in_bounds(tx, ty, w, h, margin) or not (abs(theta) < 10.0):
            return False, tx, ty, theta
        if d0 * d0 + d1 * d1 + 25.0 * d2 * d2 < min_step_sq:
            break
    return True, tx, ty, theta


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def track_point_at(
    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
    x0, y0, gx, gy, level, pattern, radius, pattern_c, radius_c, lattice, lattice_c, lattice_ws, margin,
    iterations, st, data, valid, jac, aux, pt, top=-1,
):
    """:func:`track_point` with the templates of point ``pt`` of template arrays of many points
    (``st`` (N, L), ``data`` (N, L, P), ``valid`` (N, L, P), ``jac`` (N, L, P, 3), ``aux``
    (N, L, 5, 3)), read and written without making views of them. Levels above the creation
    level use ``pattern_c`` (at most P samples; its radius ``radius_c``), the creation level
    ``pattern``: a point's template on a level is always made with the same one of the two.
    ``lattice`` and ``lattice_c``: their :func:`~granite.optical_flow.patch.unit_lattice_side`;
    ``lattice_ws``: a :func:`~granite.optical_flow.patch.lattice_workspace` for the larger."""
    tx = gx
    ty = gy
    theta = 0.0
    n_levels = offs_a.shape[0]
    first = n_levels - 1 if top < 0 else min(top, n_levels - 1)
    for lvl in range(first, level - 1, -1):
        scale = float(1 << lvl)
        fine = lvl == level
        pat = pattern if fine else pattern_c
        if st[pt, lvl] < 0:
            st[pt, lvl] = make_template_at(
                buf_a, offs_a[lvl], ws_a[lvl], hs_a[lvl], x0 / scale, y0 / scale,
                pat, margin, data, valid, jac, aux, pt, lvl, lattice if fine else lattice_c, lattice_ws,
            )
        ok = st[pt, lvl] > 0
        if ok:
            ok, nx, ny, nt = track_level(
                buf_b, offs_b[lvl], ws_b[lvl], hs_b[lvl], tx / scale, ty / scale, theta,
                pat, radius if fine else radius_c, margin, iterations,
                _MIN_STEP_SQ if lvl == level else _MIN_STEP_SQ_COARSE,
                st[pt, lvl], data, valid, jac, aux, pt, lvl,
            )
            if ok:
                tx = nx * scale
                ty = ny * scale
                theta = nt
        if not ok and lvl <= level + 1:
            return False, tx, ty, theta
    return True, tx, ty, theta


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def track_point(
    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
    x0, y0, gx, gy, level, pattern, radius, margin, iterations, st, data, valid, jac, aux,
    top=-1,
):
    """Track the point (x0, y0) of image A (level-0 pixels, created at ``level``) into image B,
    starting from the guess (gx, gy). Returns (ok, x, y, theta) in level-0 pixels, theta the
    patch rotation from A to B.

    ``st`` (L,) int8, ``data`` (L, P), ``valid`` (L, P), ``jac`` (L, P, 3), ``aux`` (L, 5, 3)
    hold this point's templates in image A per level: ``st[l]`` is the return value of
    :func:`make_template` (0 invalid, 1 valid, 2 valid and complete) or -1 (not computed
    yet: computed here and stored). ``top`` >= 0 starts at that level instead of the
    coarsest.
    """
    lattice = unit_lattice_side(pattern)
    return track_point_at(
        buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
        x0, y0, gx, gy, level, pattern, radius, pattern, radius, lattice, lattice,
        lattice_workspace(lattice), margin, iterations,
        st.reshape((1,) + st.shape), data.reshape((1,) + data.shape),
        valid.reshape((1,) + valid.shape), jac.reshape((1,) + jac.shape),
        aux.reshape((1,) + aux.shape), 0, top,
    )


@njit(cache=True, nogil=True)
def _one_point_templates(num_levels: int, num_samples: int):
    """Template arrays of one point in the layout of :func:`new_template_cache`."""
    return (np.empty((1, num_levels), dtype=np.int8),
            np.empty((1, num_levels, num_samples), dtype=np.float32),
            np.empty((1, num_levels, num_samples), dtype=np.bool_),
            np.empty((1, num_levels, num_samples, 3), dtype=np.float32),
            np.empty((1, num_levels, AUX_ROWS, 3), dtype=np.float32))


def new_template_cache(num_points: int, num_levels: int, num_samples: int):
    """Empty template cache ``(st, data, valid, jac, aux)`` for ``num_points`` points, all
    templates marked not computed (-1)."""
    return (
        np.full((num_points, num_levels), -1, dtype=np.int8),
        np.empty((num_points, num_levels, num_samples), dtype=np.float32),
        np.empty((num_points, num_levels, num_samples), dtype=np.bool_),
        np.empty((num_points, num_levels, num_samples, 3), dtype=np.float32),
        np.empty((num_points, num_levels, AUX_ROWS, 3), dtype=np.float32),
    )


#: Passes of :func:`track_points` (``order`` argument): each pass retries the points that are
#: not tracked yet, from its own initial displacement.
PASS_ZERO = 0  # zero motion (the reference)
PASS_GUESS = 1  # the caller's per-point predicted displacement
PASS_MEDIAN = 2  # the median displacement of the points tracked so far (retry_min_flow)
PASS_LOCAL = 3  # the median displacement of each point's nearest tracked neighbours
PASS_GUESS_FINE = 4  # the caller's guess, from ``guided_levels_above`` levels above the creation level
PASS_GUESS_NEAR = 5  # the caller's guess, from one level above the creation level

#: A guided track tracked from its creation level only (``guided_levels_above = 0``) is kept
#: there only if it ended within this many pixels (of that level) of its prediction; otherwise
#: the pass from one level above decides (docs/optical_flow.md).
_CREATION_LEVEL_REACH = 0.5

#: A local-flow retry tracks from the guess on the creation level c and this many levels above
#: it only (the guess is within a few pixels; coarser levels cost as much as fine ones and are
#: the ones that do not fit the points that need the retry). The reference also rejects a
#: track that fails on level c + 1.
_LOCAL_LEVELS_ABOVE = 1

_NO_GUESS = np.zeros((0, 2))
#: ``fallback`` of :func:`track_points` when every point may be retried by every pass.
_ALL_FALLBACK = np.zeros(0, dtype=np.bool_)
_ORDER_UNGUIDED = np.array([PASS_ZERO, PASS_MEDIAN], dtype=np.int64)
_ORDER_GUIDED = np.array([PASS_GUESS, PASS_ZERO, PASS_MEDIAN], dtype=np.int64)


def pass_order(guided: bool, local_rounds: int = 0, fine_first: bool = False,
               near_after_fine: bool = False) -> np.ndarray:
    """The passes of :func:`track_points`: [[guess from a fine level, [guess from one level
    above the creation level,]] guess,] zero, median, then ``local_rounds`` local-flow
    passes."""
    base = _ORDER_GUIDED if guided else _ORDER_UNGUIDED
    if guided and fine_first:
        first = [PASS_GUESS_FINE, PASS_GUESS_NEAR] if near_after_fine else [PASS_GUESS_FINE]
        base = np.concatenate([np.array(first, dtype=np.int64), base])
    return np.concatenate([base, np.full(max(0, local_rounds), PASS_LOCAL, dtype=np.int64)])


def track_points(
    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
    points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
    st_b, data_b, valid_b, jac_b, aux_b,
    pattern, margin, iterations, fb_threshold_sq, retry_min_flow,
    guess=None, order=None, min_zncc_guess=0.9, local_neighbours=8,
    fb_var=None, fb_max_sq=np.inf, executor=None, guided_levels_above=-1, share=None,
    pattern_coarse=None, preset=None, fallback=None,
):
    """Track all points of image A into image B with a forward-backward check.

    Args:
        points: (N, 2) float64 level-0 positions in A; levels: (N,) int64 creation levels.
        rows_a: (N,) row of each point in the template cache of image A (``*_a``), or -1.
        ``*_b``: template cache of image B with N rows (``st_b`` all -1 on entry); the
            backward pass fills row k with point k's templates at its new position, so the
            next frame can reuse them as its ``*_a`` cache.
        retry_min_flow: if > 0 and the median displacement ``f`` of the points tracked on
            the earlier passes is at least this long (level-0 pixels), the failed points are
            tracked again from the guess ``p + f`` (and back from ``p' - f``).
        guess: optional (N, 2) predicted displacement of each point (level-0 pixels; a row
            with a NaN: no prediction). The guided pass tracks ``p -> p + g`` forward
            (coarse to fine, starting from ``g`` instead of zero motion) and back from the
            found ``p'`` starting at ``p' - g``, under the same forward-backward check.
        min_zncc_guess: a match of the guided pass is accepted only if the zero-mean
            normalised cross-correlation of the patch with its template (creation level) is
            at least this (<= -1 disables). The guided backward pass starts near ``p``, so
            it cannot expose a false match that a wrong prediction led the forward pass to.
        order: (M,) int64 sequence of passes (:data:`PASS_ZERO`, :data:`PASS_GUESS`,
            :data:`PASS_MEDIAN`, :data:`PASS_LOCAL`); each pass retries the points still not
            tracked. Default: guess, zero, median with a guess; zero, median (the reference
            plus the retry) without (see :func:`pass_order`).
        fb_var: optional (L,) per level ``c``: ``kappa**2 * (sigma_A**2 + sigma_B**2)``,
            the squared noise-scaled limit factor (``sigma`` the noise of level ``c`` of each
            image, intensity units); 0 or None: the fixed limit. Where positive, a point
            created on level ``c`` is kept when its squared forward-backward distance is
            below ``clip(fb_var[c] * lambda_max(C) / mean**2, fb_threshold_sq, fb_max_sq)``,
            with ``C`` the translation block of ``(J^T J)^-1`` and ``mean`` the mean of its
            template in image A on level ``c``: ``kappa`` standard deviations of the
            forward-backward distance the image noise alone would cause (the forward and
            backward estimates taken as independent).
        local_neighbours: the local-flow pass (:data:`PASS_LOCAL`) starts each point that
            is not tracked yet from the median displacement (per axis) of the
            ``local_neighbours`` nearest points (level-0 distance) tracked by the earlier
            passes, forward from ``p + g`` and back from ``p' - g`` like the guided pass and
            under the same patch-correlation test (``min_zncc_guess``), on the creation level
            and the one above only. Needs at least 3 tracked points; guesses shorter than
            1 px, or within 2 px of where the point's earlier forward attempt ended, are
            skipped.
        share: optional :class:`~granite.optical_flow.work_share.PointShare`: the leading
            guided and zero-motion passes (per point independent) run in chunks of
            :data:`SHARE_CHUNK` points that other threads may claim meanwhile
            (:meth:`PointShare.help`, e.g. the caller's thread once it would otherwise wait
            for the result); the median and local-flow passes follow over all points, on this
            thread. The results are bit-identical to a call without it.
        executor: optional ``concurrent.futures`` executor with a free worker thread, which
            helps from the start (a share is made if none is given).
        pattern_coarse: optional pattern (at most as many samples as ``pattern``) for the
            levels above each point's creation level, which only seed the next finer level;
            default ``pattern``. The creation level, the ZNCC test and the forward-backward
            limit always use ``pattern``.
        preset: optional ``(done (N,) bool, new_points (N, 2), theta (N,))``: the points
            marked ``done`` were tracked already (their templates in B filled by the caller);
            they keep these results, the passes skip them and the median pass counts them.
        fallback: optional (N,) bool: the points the passes that ignore the predictions (zero
            motion, median flow) may retry; None: all. The frontend leaves out the tracks
            whose confirmed prediction lies outside image B (they left the view).
    Returns:
        (new_points (N, 2), theta (N,), status (N,) bool): status is True when the point was
        tracked A -> B and back B -> A to within ``fb_threshold_sq`` (squared distance in
        pixels of its creation level) of its start. Without a guess the first pass starts
        both directions from zero motion, as the reference does. ``new_points`` of a point
        that failed every pass is the forward result of its first attempt.
    """
    if guess is None:
        guess = _NO_GUESS
    else:
        guess = np.ascontiguousarray(guess, dtype=np.float64)
        if guess.shape != (points.shape[0], 2):
            raise ValueError(f"guess must have shape ({points.shape[0]}, 2), got {guess.shape}")
    if order is None:
        order = _ORDER_UNGUIDED if guess.shape[0] == 0 else _ORDER_GUIDED
    n_levels = offs_a.shape[0]
    fb_var = np.zeros(n_levels) if fb_var is None else np.ascontiguousarray(fb_var, dtype=np.float64)
    if fb_var.shape != (n_levels,):
        raise ValueError(f"fb_var must have shape ({n_levels},), got {fb_var.shape}")
    order = np.ascontiguousarray(order, dtype=np.int64)
    pattern_c = pattern if pattern_coarse is None else np.ascontiguousarray(pattern_coarse, dtype=np.float64)
    if pattern_c.shape[0] > pattern.shape[0]:
        raise ValueError(f"pattern_coarse has {pattern_c.shape[0]} samples, more than the "
                         f"pattern's {pattern.shape[0]} (the template rows)")
    args = (
        buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
        points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
        st_b, data_b, valid_b, jac_b, aux_b,
        pattern, pattern_c, margin, iterations, fb_threshold_sq, retry_min_flow, guess,
    )
    if fallback is None:
        fallback = _ALL_FALLBACK
    else:
        fallback = np.ascontiguousarray(fallback, dtype=np.bool_)
        if fallback.shape != (points.shape[0],):
            raise ValueError(f"fallback must have shape ({points.shape[0]},), got {fallback.shape}")
    tail = (float(min_zncc_guess), int(local_neighbours), fb_var, float(fb_max_sq),
            int(guided_levels_above), fallback)
    n = points.shape[0]
    if share is None and executor is not None:
        share = PointShare()
    if preset is None and (share is None or n < _MIN_SHARED):
        if share is not None:
            share.close()
        return _track_points(*args, order, *tail)[:3]
    state = _pass_state(n)
    if preset is not None:
        done, done_points, done_theta = preset
        done = np.asarray(done, dtype=np.bool_)
        state[0][done], state[1][done] = done_points[done], done_theta[done]
        state[2][done] = True  # status
        state[3][done] = True  # tried
    if share is None or n < _MIN_SHARED:
        if share is not None:
            share.close()
        _track_passes(*args, order, *tail, 0, n, *state)
        return state[0], state[1], state[2]
    m = independent_passes(order)
    if executor is not None:
        executor.submit(share.help)
    share.run(lambda: _track_passes_claimed(*args, order[:m], *tail, share.counter, SHARE_CHUNK,
                                            *state))
    _track_passes(*args, order[m:], *tail, 0, n, *state)
    out, theta, status = state[:3]
    return out, theta, status


#: Fewer points than this are tracked in one thread.
_MIN_SHARED = 32
#: Points per claimed chunk of a shared call (~0.2 ms of work at 640x480; claiming one costs
#: an atomic increment).
SHARE_CHUNK = 16


def independent_passes(order: np.ndarray) -> int:
    """Number of leading passes of ``order`` that treat each point on its own (guided and
    zero-motion passes): those may be split over disjoint point ranges."""
    m = 0
    while m < len(order) and int(order[m]) in (PASS_ZERO, PASS_GUESS, PASS_GUESS_FINE, PASS_GUESS_NEAR):
        m += 1
    return m


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _track_points(
    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
    points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
    st_b, data_b, valid_b, jac_b, aux_b,
    pattern, pattern_c, margin, iterations, fb_threshold_sq, retry_min_flow, guess, order, min_zncc_guess,
    local_neighbours, fb_var, fb_max_sq, guided_levels_above, fallback,
):
    """Kernel of :func:`track_points` (``guess`` (N, 2) or (0, 2) for none). Also returns
    the ZNCC of each point's last guided forward match (-2: none)."""
    n = points.shape[0]
    out, theta, status, tried, score, local = _pass_state(n)
    _track_passes(
        buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
        points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
        st_b, data_b, valid_b, jac_b, aux_b,
        pattern, pattern_c, margin, iterations, fb_threshold_sq, retry_min_flow, guess, order, min_zncc_guess,
        local_neighbours, fb_var, fb_max_sq, guided_levels_above, fallback, 0, n, out, theta, status, tried,
        score, local,
    )
    return out, theta, status, score


@njit(cache=True, fastmath=_FASTMATH, error_model="numpy")
def _fits_level(x, y, lvl, ws, hs, pattern, radius, margin):
    """Whether a patch centred at the level-0 point (x, y) fits level ``lvl`` as a template
    needs it (:func:`~granite.optical_flow.patch.make_template_at`): its centre and more than
    half of its samples inside (``margin``)."""
    scale = float(1 << lvl)
    cx = x / scale
    cy = y / scale
    w = ws[lvl]
    h = hs[lvl]
    if not in_bounds(cx, cy, w, h, margin):
        return False
    if in_bounds(cx, cy, w, h, margin + radius):
        return True
    n = pattern.shape[0]
    inside = 0
    for i in range(n):
        inside += in_bounds(cx + pattern[i, 0], cy + pattern[i, 1], w, h, margin)
    return 2 * inside > n


@njit(cache=True, nogil=True)
def _pass_state(n):
    """Per-point state of the passes: ``out`` (N, 2), ``theta``, ``status``, ``tried``,
    ``score`` and the local-flow guesses ``local`` (N, 2)."""
    return (np.empty((n, 2)), np.zeros(n), np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_),
            np.full(n, -2.0), np.full((n, 2), np.nan))


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _track_passes_claimed(
    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
    points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
    st_b, data_b, valid_b, jac_b, aux_b,
    pattern, pattern_c, margin, iterations, fb_threshold_sq, retry_min_flow, guess, order, min_zncc_guess,
    local_neighbours, fb_var, fb_max_sq, guided_levels_above, fallback, counter, chunk, out, theta, status,
    tried, score, local,
):
    """:func:`_track_passes` of per point independent passes over chunks of ``chunk`` points
    claimed from ``counter[0]`` (atomically, :func:`fetch_add`) until none is left: any
    number of threads may run it at once on the same state."""
    n = points.shape[0]
    while True:
        k0 = fetch_add(counter, 0, chunk)
        if k0 >= n:
            return
        _track_passes(
            buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
            points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
            st_b, data_b, valid_b, jac_b, aux_b,
            pattern, pattern_c, margin, iterations, fb_threshold_sq, retry_min_flow, guess, order, min_zncc_guess,
            local_neighbours, fb_var, fb_max_sq, guided_levels_above, fallback, k0, min(k0 + chunk, n), out, theta,
            status, tried, score, local,
        )


@njit(cache=True, nogil=True, fastmath=_FASTMATH, error_model="numpy")
def _track_passes(
    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
    points, levels, rows_a, st_a, data_a, valid_a, jac_a, aux_a,
    st_b, data_b, valid_b, jac_b, aux_b,
    pattern, pattern_c, margin, iterations, fb_threshold_sq, retry_min_flow, guess, order, min_zncc_guess,
    local_neighbours, fb_var, fb_max_sq, guided_levels_above, fallback, k0, k1, out, theta, status, tried,
    score, local,
):
    """The passes ``order`` of :func:`_track_points` for the points ``k0 <= k < k1``, on the
    per-point state (``out``, ``theta``, ``status``, ``tried``, ``score``, ``local``, all N
    rows, updated in place). A zero-motion or guided pass of one point reads and writes only
    that point's rows (its template rows ``rows_a[k]`` in A and ``k`` in B included), so
    disjoint ranges of such passes may run concurrently, with results identical to one call
    over all points; the median and local-flow passes read every point's state."""
    n = points.shape[0]
    n_levels = offs_a.shape[0]
    p = pattern.shape[0]
    has_guess = guess.shape[0] == n and n > 0
    has_fallback = fallback.shape[0] == n
    # templates of points without a cached row: point 0 of one-point template arrays
    st_s, data_s, valid_s, jac_s, aux_s = _one_point_templates(n_levels, p)
    radius = pattern_radius(pattern)
    radius_c = pattern_radius(pattern_c)
    lattice = unit_lattice_side(pattern)
    lattice_c = unit_lattice_side(pattern_c)
    lattice_ws = lattice_workspace(max(lattice, lattice_c))
    for mode in order:
        flow_x = 0.0
        flow_y = 0.0
        guided = mode == PASS_GUESS or mode == PASS_GUESS_FINE or mode == PASS_GUESS_NEAR
        if guided and not has_guess:
            continue
        if mode == PASS_LOCAL:
            if not local_guesses(points, out, status, local_neighbours, local):
                continue
        if mode == PASS_MEDIAN:
            # Median displacement of the earlier passes as the guess for the failed points.
            n_ok = 0
            for k in range(n):
                n_ok += status[k]
            if retry_min_flow <= 0.0 or n_ok < 5 or n_ok == n:
                continue
            dx = np.empty(n_ok)
            dy = np.empty(n_ok)
            j = 0
            for k in range(n):
                if status[k]:
                    dx[j] = out[k, 0] - points[k, 0]
                    dy[j] = out[k, 1] - points[k, 1]
                    j += 1
            flow_x = np.median(dx)
            flow_y = np.median(dy)
            if flow_x * flow_x + flow_y * flow_y < retry_min_flow * retry_min_flow:
                continue
        blind = mode == PASS_ZERO or mode == PASS_MEDIAN  # passes that ignore the predictions
        for k in range(k0, k1):
            if status[k]:
                continue
            if blind and has_fallback and not fallback[k]:
                continue
            per_point = guided or mode == PASS_LOCAL
            if per_point:
                if mode != PASS_LOCAL:
                    flow_x = guess[k, 0]
                    flow_y = guess[k, 1]
                else:
                    flow_x = local[k, 0]
                    flow_y = local[k, 1]
                if not (math.isfinite(flow_x) and math.isfinite(flow_y)):
                    continue
            x0 = points[k, 0]
            y0 = points[k, 1]
            lvl = levels[k]
            row = rows_a[k]
            top = -1
            if mode == PASS_LOCAL:
                top = lvl + _LOCAL_LEVELS_ABOVE
            elif mode == PASS_GUESS_FINE:
                top = lvl + guided_levels_above
            elif mode == PASS_GUESS_NEAR:
                top = lvl + 1
            # From the creation level only, the level above must still hold the patch (in A
            # here, in B below), as the coarse-to-fine passes require: the accepted tracks stay
            # those of the passes that start higher.
            check_above = mode == PASS_GUESS_FINE and guided_levels_above == 0 and lvl + 1 < n_levels
            if check_above and not _fits_level(x0, y0, lvl + 1, ws_a, hs_a, pattern_c, radius_c, margin):
                continue
            if row >= 0:
                ok, x1, y1, t1 = track_point_at(
                    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
                    x0, y0, x0 + flow_x, y0 + flow_y, lvl, pattern, radius, pattern_c, radius_c, lattice, lattice_c, lattice_ws, margin,
                    iterations,
                    st_a, data_a, valid_a, jac_a, aux_a, row, top,
                )
            else:
                st_s[0, :] = -1
                ok, x1, y1, t1 = track_point_at(
                    buf_a, offs_a, ws_a, hs_a, buf_b, offs_b, ws_b, hs_b,
                    x0, y0, x0 + flow_x, y0 + flow_y, lvl, pattern, radius, pattern_c, radius_c, lattice, lattice_c, lattice_ws, margin,
                    iterations,
                    st_s, data_s, valid_s, jac_s, aux_s, 0, top,
                )
            if ok and per_point and min_zncc_guess > -1.0:
                # The backward pass below starts near the start point, so a false match
                # found from a wrong prediction can pass the forward-backward check; require
                # the patch to look like its template.
                scale = float(1 << lvl)
                if row >= 0:
                    zn = patch_zncc_at(
                        buf_b, offs_b[lvl], ws_b[lvl], hs_b[lvl], x1 / scale, y1 / scale, t1,
                        pattern, radius, margin, st_a[row, lvl], data_a, valid_a, row, lvl,
                    )
                else:
                    zn = patch_zncc_at(
                        buf_b, offs_b[lvl], ws_b[lvl], hs_b[lvl], x1 / scale, y1 / scale, t1,
                        pattern, radius, margin, st_s[0, lvl], data_s, valid_s, 0, lvl,
                    )
                score[k] = zn
                ok = zn >= min_zncc_guess
            if ok and check_above:
                # and the match must lie within the creation level's reach of the prediction:
                # farther, the patch may have settled in a neighbouring minimum, which the pass
                # from the level above (twice the reach) tells apart
                scale = float(1 << lvl)
                moved_sq = ((x1 - x0 - flow_x) ** 2 + (y1 - y0 - flow_y) ** 2) / (scale * scale)
                ok = (moved_sq < _CREATION_LEVEL_REACH ** 2
                      and _fits_level(x1, y1, lvl + 1, ws_b, hs_b, pattern_c, radius_c, margin))
            if ok or not tried[k]:
                out[k, 0] = x1
                out[k, 1] = y1
                theta[k] = t1
            tried[k] = True
            if not ok:
                continue
            st_b[k, :] = -1  # templates at a new position
            ok, xb, yb, _ = track_point_at(
                buf_b, offs_b, ws_b, hs_b, buf_a, offs_a, ws_a, hs_a,
                x1, y1, x1 - flow_x, y1 - flow_y, lvl, pattern, radius, pattern_c, radius_c, lattice, lattice_c, lattice_ws, margin,
                    iterations,
                st_b, data_b, valid_b, jac_b, aux_b, k, top,
            )
            if not ok:
                continue
            scale = float(1 << lvl)
            dist_sq = ((xb - x0) ** 2 + (yb - y0) ** 2) / (scale * scale)
            limit_sq = fb_threshold_sq
            if fb_var[lvl] > 0.0:
                a = aux_a[row, lvl] if row >= 0 else aux_s[0, lvl]
                mean = float(a[4, 0])
                limit_sq = min(max(fb_var[lvl] * translation_lambda_max(a) / (mean * mean), fb_threshold_sq), fb_max_sq)
            status[k] = dist_sq < limit_sq
