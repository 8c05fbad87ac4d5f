"""Sliding-window bundle adjustment backend (paper Sec. IV, IV-B, IV-C; Basalt-style).

Frames and units (docs/conventions.md): poses are ``T_w_c`` (4,4), camera x right / y down /
z forward; pose increments are the decoupled twist ``[v, w]`` of paper Eq. 14; landmarks are
a bearing in their host keyframe plus an inverse distance ``d >= 0`` (``d = 0``: at infinity).
See ``docs/backend.md``.
"""

from granite.backend.config import BackendConfig
from granite.backend.hessian import WindowHessian, marginal_information, marginalize_dense
from granite.backend.landmarks import Landmark, LandmarkDatabase, Observation
from granite.backend.marginalization import MarginalizationReport
from granite.backend.priors import MargPrior, ScaleFix, pose_delta
from granite.backend.problem import WindowProblem, WorkspacePool
from granite.backend.scale_drift import (
    KeyframeSystem,
    ScaleDriftResult,
    chain_jacobian,
    chain_jacobian_inverse,
    indicator_from_information,
    keyframe_system,
    relative_poses,
    relative_translation_information,
    scale_drift_indicator,
    scale_drift_of_system,
    scale_drift_task,
)
from granite.backend.solver import OptimizeReport
from granite.backend.window import FrameState, SlidingWindow

__all__ = [
    "BackendConfig",
    "SlidingWindow",
    "OptimizeReport",
    "MarginalizationReport",
    "FrameState",
    "WindowProblem",
    "WorkspacePool",
    "WindowHessian",
    "MargPrior",
    "ScaleFix",
    "Landmark",
    "LandmarkDatabase",
    "Observation",
    "marginalize_dense",
    "marginal_information",
    "pose_delta",
    "KeyframeSystem",
    "ScaleDriftResult",
    "chain_jacobian",
    "chain_jacobian_inverse",
    "indicator_from_information",
    "keyframe_system",
    "relative_poses",
    "relative_translation_information",
    "scale_drift_indicator",
    "scale_drift_of_system",
    "scale_drift_task",
]
