"""Common base of the camera models.

Frames and units: 3-D points are in the camera frame (x right, y down, z forward, any length
unit); pixels are ``(u, v) = (column, row)`` with the centre of the top-left pixel at (0, 0).
Bearings are unit vectors in the camera frame.

Every method is vectorised over N points (numba kernels, no Python loop over points).
Entries flagged invalid have all their outputs (pixels, bearings, Jacobians) set to 0, so
they are finite and can be masked or weighted to zero safely; NaN/inf input is invalid.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from granite.camera import batch
from granite.errors import ConfigError


def _as_array(a: np.ndarray, cols: int, what: str) -> np.ndarray:
    arr = np.ascontiguousarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != cols:
        raise ValueError(f"{what} must have shape (N, {cols}), got {np.shape(a)}")
    return arr


class CameraModel:
    """Base class: subclasses set ``name``, ``param_names`` and ``kernel_model``, the id under
    which their per-point kernels are registered in :mod:`granite.camera.batch`."""

    name: ClassVar[str] = ""
    param_names: ClassVar[tuple[str, ...]] = ()
    kernel_model: ClassVar[int]

    def __init__(self, params: np.ndarray, width: int, height: int) -> None:
        """``params``: intrinsics in Basalt order (``param_names``); ``width``/``height``:
        image size in pixels. Raises :class:`ConfigError` for bad values."""
        try:
            p = np.array(params, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise ConfigError(f"camera '{self.name}': parameters must be numbers, got {params!r}") from None
        if p.size != len(self.param_names):
            raise ConfigError(
                f"camera '{self.name}' needs {len(self.param_names)} parameters "
                f"({' '.join(self.param_names)}), got {p.size}"
            )
        for n, val in zip(self.param_names, p):
            if not math.isfinite(val):
                raise ConfigError(f"camera '{self.name}': parameter {n} is not finite ({val})")
        if not (p[0] > 0.0 and p[1] > 0.0):
            raise ConfigError(f"camera '{self.name}': fx and fy must be positive, got {p[0]}, {p[1]}")
        for n, val in (("width", width), ("height", height)):
            try:
                ok = not isinstance(val, (bool, np.bool_)) and float(val).is_integer() and int(val) > 0
            except (TypeError, ValueError, OverflowError):
                ok = False
            if not ok:
                raise ConfigError(f"camera '{self.name}': {n} must be a positive integer, got {val!r}")
        self.width = int(width)
        self.height = int(height)
        p.setflags(write=False)
        self.params = p
        self._kparams = np.ascontiguousarray(self._kernel_params(p), dtype=np.float64)

    # ------------------------------------------------------------------ hooks
    def _kernel_params(self, p: np.ndarray) -> np.ndarray:
        """Validate model-specific ranges; return the parameter vector the kernels get
        (may append precomputed constants)."""
        return p.copy()

    # ------------------------------------------------------------------ API
    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def kernel_params(self) -> np.ndarray:
        """Parameter vector the numba kernels take (``params`` followed by precomputed
        constants), for calling e.g. ``batch.project_points(cam.kernel_model,
        cam.kernel_params, points, True)`` from inside njit code."""
        return self._kparams

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``uv`` (N,2) of camera-frame points (N,3), and ``valid`` (N,) bool."""
        pts = _as_array(points, 3, "points")
        uv, _, _, valid = batch.project_points(self.kernel_model, self._kparams, pts, False)
        return uv, valid

    def project_jacobians(
        self, points: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(uv (N,2), d_uv_d_point (N,2,3), d_uv_d_params (N,2,P), valid (N,))``;
        parameter derivatives are in ``param_names`` order."""
        pts = _as_array(points, 3, "points")
        return batch.project_points(self.kernel_model, self._kparams, pts, True)

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit bearings (N,3) in the camera frame of pixels (N,2), and ``valid`` (N,)."""
        pix = _as_array(uv, 2, "uv")
        b, _, valid = batch.unproject_pixels(self.kernel_model, self._kparams, pix, False)
        return b, valid

    def unproject_jacobians(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(bearings (N,3), d_bearing_d_uv (N,3,2), valid (N,))``."""
        pix = _as_array(uv, 2, "uv")
        return batch.unproject_pixels(self.kernel_model, self._kparams, pix, True)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True where ``margin <= u <= width - 1 - margin`` and ``margin <= v <= height - 1 -
        margin`` (pixel-centre coordinates; NaN gives False)."""
        pix = np.asarray(uv, dtype=np.float64)
        if pix.ndim != 2 or pix.shape[1] != 2:
            raise ValueError(f"uv must have shape (N, 2), got {pix.shape}")
        u = pix[:, 0]
        v = pix[:, 1]
        return (
            (u >= margin)
            & (u <= self.width - 1 - margin)
            & (v >= margin)
            & (v <= self.height - 1 - margin)
        )

    def to_basalt(self) -> tuple[str, dict[str, float]]:
        """``(camera_type, intrinsics)`` with Basalt's names; inverse of ``make_camera``."""
        return self.name, {n: float(v) for n, v in zip(self.param_names, self.params)}

    def __repr__(self) -> str:
        vals = ", ".join(f"{n}={v:.6g}" for n, v in zip(self.param_names, self.params))
        return f"{type(self).__name__}({vals}, width={self.width}, height={self.height})"
