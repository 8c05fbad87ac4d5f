"""Optical-flow frontend: multi-level FAST detection and KLT patch tracking (paper Sec. IV-A).

Modules mirror the reference: :mod:`.patterns` (sampling pattern), :mod:`.patch` and
:mod:`.tracking` (numba kernels), :mod:`.detection` (grid FAST on pyramid levels),
:mod:`.frame_to_frame` (the stateful tracker). Positions are level-0 pixels, the centre of the
top-left pixel being (0, 0); see ``docs/optical_flow.md``.
"""

from granite.optical_flow.config import OpticalFlowConfig
from granite.optical_flow.frame_to_frame import (
    FrameRejectedWarning,
    FrameToFrameOpticalFlow,
    OpticalFlowResult,
)
from granite.optical_flow.pyramid import ImagePyramid, build_pyramid

__all__ = [
    "FrameRejectedWarning",
    "FrameToFrameOpticalFlow",
    "ImagePyramid",
    "OpticalFlowConfig",
    "OpticalFlowResult",
    "build_pyramid",
]
