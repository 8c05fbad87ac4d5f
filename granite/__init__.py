"""granite-py: robust monocular visual odometry for flying robots (Wudenka et al., IROS 2021).

Conventions used throughout the package:

* Poses are 4x4 homogeneous matrices. ``T_a_b`` maps points from frame ``b`` into frame ``a``
  (``p_a = T_a_b @ p_b``); ``T_w_c`` is the camera-to-world pose.
* Cameras use the computer-vision convention: x right, y down, z forward (optical axis).
* Timestamps are seconds (float64) in memory and in TUM files, integer nanoseconds in
  EuRoC/ASL files.
* Quaternions are Hamilton, stored ``(qx, qy, qz, qw)`` as in TUM files.
"""

__version__ = "0.1.0"

# Before any kernel is compiled: numba's on-disk cache keyed by a hash of these sources
# (granite/_numba_cache.py), so that it is always valid.
from granite._numba_cache import configure_numba_cache as _configure_numba_cache  # noqa: E402

_configure_numba_cache()

# Kernels loaded from that cache keep their LLVM IR as bitcode, parsed only if another kernel
# links them (granite/_numba_linking.py): ~54 MB less resident memory in a VO run.
from granite._numba_linking import install_when_numba_loads as _lazy_linking_ir  # noqa: E402

_lazy_linking_ir()
