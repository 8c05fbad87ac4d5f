"""Lie-group geometry (SO(3), SE(3), Sim(3)), pose interpolation, alignment and quaternions.

Conventions (docs/conventions.md): poses are 4x4 float64 matrices, ``T_a_b`` maps points of
frame ``b`` into ``a``; se(3) twists are ``[v, w]`` (translation first), sim(3) vectors
``[v, w, sigma]`` with scale ``exp(sigma)``; quaternions are Hamilton ``xyzw``.

The single-element kernels (``hat, vee, so3_*, se3_*, decoupled_increment, sim3_*``) are
``numba.njit(cache=True)`` functions on float64 numpy arrays, usable inside other njit code.
"""

from granite.geometry.alignment import umeyama_alignment
from granite.geometry.interpolation import interpolate_poses
from granite.geometry.quaternion import quat_to_rotation, rotation_to_quat
from granite.geometry.se3 import (
    decoupled_increment,
    se3_adjoint,
    se3_compose,
    se3_exp,
    se3_inverse,
    se3_log,
)
from granite.geometry.sim3 import sim3_exp, sim3_log
from granite.geometry.so3 import (
    hat,
    kabsch_rotation,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_right_jacobian,
    so3_right_jacobian_inv,
    vee,
)

__all__ = [
    "hat",
    "kabsch_rotation",
    "vee",
    "so3_exp",
    "so3_log",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "se3_exp",
    "se3_log",
    "se3_inverse",
    "se3_compose",
    "se3_adjoint",
    "decoupled_increment",
    "sim3_exp",
    "sim3_log",
    "interpolate_poses",
    "umeyama_alignment",
    "quat_to_rotation",
    "rotation_to_quat",
]
