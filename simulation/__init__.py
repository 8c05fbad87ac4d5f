"""Blender Mars test-bench: procedural Mars-analogue terrain, smooth drone flights and
headless Cycles rendering with exact ground truth (poses, calibration, planar depth).

Only this package imports ``bpy`` (in :mod:`simulation.render` and
:mod:`simulation.terrain.scene`); everything else (scenarios, flights, terrain model, output
layout) is pure numpy. Command line: ``granite-sim`` (:mod:`simulation.cli`); see
``docs/simulation.md``.
"""

import os as _os

# The renderer reads Blender's EXR output with OpenCV, which needs this before its first
# EXR read (set here, before any module of the package can import cv2).
_os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
