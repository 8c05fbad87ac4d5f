"""Build cameras from Basalt-style ``(camera_type, intrinsics)`` descriptions."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from granite.camera.base import CameraModel
from granite.camera.double_sphere import DoubleSphereCamera
from granite.camera.kannala_brandt import KannalaBrandtCamera
from granite.camera.pinhole import PinholeCamera
from granite.errors import ConfigError

CAMERA_MODELS: dict[str, type[CameraModel]] = {
    "pinhole": PinholeCamera,
    "kb4": KannalaBrandtCamera,
    "ds": DoubleSphereCamera,
}


def make_camera(
    camera_type: str, intrinsics: Mapping[str, float], width: int, height: int
) -> CameraModel:
    """Camera of Basalt type ``camera_type`` (``pinhole``, ``kb4`` or ``ds``) from a mapping
    of Basalt intrinsics names (pinhole: fx fy cx cy; kb4: + k1 k2 k3 k4; ds: + xi alpha) and
    the image size in pixels. Raises :class:`ConfigError` (one line) for an unknown type, a
    missing, unknown or non-finite parameter, or an invalid size."""
    cls = CAMERA_MODELS.get(camera_type) if isinstance(camera_type, str) else None
    if cls is None:
        raise ConfigError(
            f"unknown camera type {camera_type!r}; supported: {', '.join(CAMERA_MODELS)}"
        )
    if not isinstance(intrinsics, Mapping):
        raise ConfigError(f"camera '{camera_type}': intrinsics must be a mapping of name -> value")
    missing = [n for n in cls.param_names if n not in intrinsics]
    if missing:
        raise ConfigError(
            f"camera '{camera_type}': missing intrinsics {', '.join(missing)} "
            f"(needs {' '.join(cls.param_names)})"
        )
    unknown = [str(n) for n in intrinsics if n not in cls.param_names]
    if unknown:
        raise ConfigError(
            f"camera '{camera_type}': unknown intrinsics {', '.join(unknown)} "
            f"(expects {' '.join(cls.param_names)})"
        )
    values = []
    for n in cls.param_names:
        raw = intrinsics[n]
        try:
            if isinstance(raw, (bool, np.bool_)):
                raise TypeError
            val = float(raw)
        except (TypeError, ValueError):
            raise ConfigError(f"camera '{camera_type}': intrinsic {n} is not a number ({raw!r})") from None
        if not math.isfinite(val):
            raise ConfigError(f"camera '{camera_type}': intrinsic {n} is not finite ({raw!r})")
        values.append(val)
    return cls(np.array(values), width, height)  # the model checks the image size
