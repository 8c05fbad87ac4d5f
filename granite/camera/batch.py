"""The camera models' batch kernels: one loop for every model, over N points.

A model provides two per-point numba kernels and registers them with :func:`register_model`:
``project_one(kp, points, i, uv, jp, jk, want_jac) -> ok`` writes row ``i`` of the pixels
``uv`` (N,2) and, with ``want_jac``, of ``d uv / d point`` ``jp`` (N,2,3) and
``d uv / d intrinsics`` ``jk`` (N,2,P); ``unproject_one(kp, uv, i, b, jb, want_jac) -> ok``
writes the unit bearing ``b`` (N,3) and ``d b / d uv`` ``jb`` (N,3,2). ``kp`` is the camera's
``kernel_params`` (intrinsics in Basalt order, then precomputed constants). The batch loops
apply the validity rule: a projection is valid when the model accepts the point and the pixel
is finite, an unprojection when the model accepts the pixel; models registered with
``check_jacobians`` also need finite Jacobians. Invalid entries have every output 0. Without
``want_jac`` the Jacobian arrays are empty (shape ``(0, ...)``).

The loop is written once, as numba overloads specialised per model at compile time (a kernel
passed as an argument could not be cached, and a shared helper taking arrays is not inlined),
so it runs about as fast as a loop written for the model. :func:`project_points` and
:func:`unproject_pixels` are the entry points, from Python or njit code;
:func:`project_point` projects one row with the same rule from njit code that loops over
points itself (the backend's fused linearisation).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import types
from numba.extending import overload

PINHOLE = 0
KB4 = 1
DS = 2

#: model id -> (project_one, unproject_one, number of intrinsics, check_jacobians)
_MODELS: dict[int, tuple] = {}


def register_model(model: int, project_one, unproject_one, n_intrinsics: int,
                   check_jacobians: tuple[bool, bool]) -> None:
    """Make a model's per-point kernels known to the batch loops (at import of its module).
    ``check_jacobians``: whether a valid projection / unprojection also needs finite
    Jacobians (each model keeps the rule it was written and tested with)."""
    _MODELS[model] = (project_one, unproject_one, n_intrinsics, check_jacobians)


def _batch_project(model, kp, points, want_jac):
    """Typing stub of the projection loop (njit only)."""
    raise NotImplementedError


def _batch_unproject(model, kp, uv, want_jac):
    """Typing stub of the unprojection loop (njit only)."""
    raise NotImplementedError


def num_intrinsics(model: int) -> int:
    """Number of intrinsics of a registered model (the width of ``d uv / d intrinsics``)."""
    return _MODELS[model][2]


def _constants(model, want_jac):
    """``(registered model entry, want_jac)`` when both arguments are compile-time constants
    (the loops are specialised on them), else None."""
    if isinstance(model, types.IntegerLiteral) and isinstance(want_jac, types.BooleanLiteral):
        return _MODELS[model.literal_value], want_jac.literal_value
    return None


def project_point(model, kp, points, i, uv, jp, jk, want_jac):
    """Row ``i`` of :func:`project_points` into ``uv``, ``jp``, ``jk`` (njit only; ``model``
    and ``want_jac`` compile-time constants): returns the validity, and on an invalid row
    every output of row ``i`` is 0. For kernels that project point by point (the fused
    linearisation of the backend) with exactly the batch loop's rule."""
    raise NotImplementedError


@overload(project_point, prefer_literal=True, jit_options={"cache": True})
def _project_point_checked(model, kp, points, i, uv, jp, jk, want_jac):
    if (constants := _constants(model, want_jac)) is None:
        return None
    (project_one, _, nk, (check, _)), jac = constants

    def one(model, kp, points, i, uv, jp, jk, want_jac):
        if jac:  # the models write only the non-zero Jacobian entries
            for a in range(2):
                for c in range(3):
                    jp[i, a, c] = 0.0
                for c in range(nk):
                    jk[i, a, c] = 0.0
        ok = project_one(kp, points, i, uv, jp, jk, jac)
        ok = ok and math.isfinite(uv[i, 0]) and math.isfinite(uv[i, 1])
        if ok and jac and check:
            for a in range(2):
                for c in range(3):
                    ok = ok and math.isfinite(jp[i, a, c])
                for c in range(nk):
                    ok = ok and math.isfinite(jk[i, a, c])
        if not ok:
            uv[i, 0] = 0.0
            uv[i, 1] = 0.0
            if jac:
                for a in range(2):
                    for c in range(3):
                        jp[i, a, c] = 0.0
                    for c in range(nk):
                        jk[i, a, c] = 0.0
        return ok

    return one


@overload(_batch_project, prefer_literal=True, jit_options={"cache": True})
def _batch_project_loop(model, kp, points, want_jac):
    if (constants := _constants(model, want_jac)) is None:
        return None
    (_, _, nk, _), jac = constants
    model_id = model.literal_value

    def loop(model, kp, points, want_jac):
        n = points.shape[0]
        m = n if jac else 0
        uv = np.empty((n, 2))
        jp = np.empty((m, 2, 3))
        jk = np.empty((m, 2, nk))
        valid = np.empty(n, dtype=np.bool_)
        for i in range(n):
            valid[i] = project_point(model_id, kp, points, i, uv, jp, jk, jac)
        return uv, jp, jk, valid

    return loop


@overload(_batch_unproject, prefer_literal=True, jit_options={"cache": True})
def _batch_unproject_loop(model, kp, uv, want_jac):
    if (constants := _constants(model, want_jac)) is None:
        return None
    (_, unproject_one, _, (_, check)), jac = constants

    def loop(model, kp, uv, want_jac):
        n = uv.shape[0]
        b = np.zeros((n, 3))
        jb = np.zeros((n if jac else 0, 3, 2))
        valid = np.zeros(n, dtype=np.bool_)
        for i in range(n):
            ok = unproject_one(kp, uv, i, b, jb, jac)
            if ok and jac and check:
                for a in range(3):
                    ok = ok and math.isfinite(jb[i, a, 0]) and math.isfinite(jb[i, a, 1])
            valid[i] = ok
            if not ok:
                b[i, :] = 0.0
                if jac:
                    jb[i, :, :] = 0.0
        return b, jb, valid

    return loop


_PROJECT = 0
_UNPROJECT = 1


def _by_model(operation, model, kp, values, want_jac):
    """Typing stub of the dispatch to the loop of one model (njit only)."""
    raise NotImplementedError


@overload(_by_model, prefer_literal=True, jit_options={"cache": True})
def _by_model_dispatch(operation, model, kp, values, want_jac):
    """Model id and ``want_jac`` are run-time values; the loops need them as compile-time
    constants (so that each model's kernel is inlined and, without Jacobians, trimmed)."""
    if not isinstance(operation, types.IntegerLiteral):
        return None
    loop = _batch_project if operation.literal_value == _PROJECT else _batch_unproject

    def dispatch(operation, model, kp, values, want_jac):
        if want_jac:
            if model == KB4:
                return loop(KB4, kp, values, True)
            if model == DS:
                return loop(DS, kp, values, True)
            return loop(PINHOLE, kp, values, True)
        if model == KB4:
            return loop(KB4, kp, values, False)
        if model == DS:
            return loop(DS, kp, values, False)
        return loop(PINHOLE, kp, values, False)

    return dispatch


@numba.njit(cache=True, nogil=True)
def project_points(model: int, kp: np.ndarray, points: np.ndarray, want_jac: bool):
    """``(uv (N,2), d_uv_d_point (N,2,3), d_uv_d_intrinsics (N,2,P), valid (N,))`` of
    camera-frame points (N,3)."""
    return _by_model(_PROJECT, model, kp, points, want_jac)


@numba.njit(cache=True, nogil=True)
def unproject_pixels(model: int, kp: np.ndarray, uv: np.ndarray, want_jac: bool):
    """``(bearings (N,3), d_bearing_d_uv (N,3,2), valid (N,))`` of pixels (N,2)."""
    return _by_model(_UNPROJECT, model, kp, uv, want_jac)
