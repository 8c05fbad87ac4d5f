"""Camera calibration in Basalt's JSON format (``calib.json``).

Layout (only ``value0.intrinsics[0]`` and ``value0.resolution[0]`` are required on read;
``value0.T_imu_cam[0]`` defaults to the identity)::

    {"value0": {
        "T_imu_cam": [{"px": 0, "py": 0, "pz": 0, "qx": 0, "qy": 0, "qz": 0, "qw": 1}],
        "intrinsics": [{"camera_type": "pinhole",
                        "intrinsics": {"fx": .., "fy": .., "cx": .., "cy": ..}}],
        "resolution": [[width, height]],
        "vignette": [], "calib_accel_bias": [0 x 9], "calib_gyro_bias": [0 x 12],
        "imu_update_rate": 200.0, "accel_noise_std": [..], "gyro_noise_std": [..],
        "accel_bias_std": [..], "gyro_bias_std": [..], "cam_time_offset_ns": 0}}

Camera types and parameter names (Basalt's): ``pinhole`` fx fy cx cy; ``kb4`` fx fy cx cy
k1 k2 k3 k4; ``ds`` fx fy cx cy xi alpha; ``pinhole-radtan8`` fx fy cx cy k1 k2 p1 p2 and the
optional k3 k4 k5 k6 (default 0; OpenCV's rational radial-tangential model; Basalt's ``rpmax``
is ignored). The first three are the VO's camera models; a ``pinhole-radtan8`` camera's images
are undistorted to a pinhole camera when the dataset reads them (:mod:`granite.io.undistortion`).
``T_imu_cam`` maps camera points into the IMU / body frame; the quaternion is Hamilton.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from granite.errors import ConfigError, InputError
from granite.io._poses import pose_from_pq, pq_from_poses
from granite.io._text import QUAT_NORM_TOL, read_text
from granite.io.atomic import atomic_write_text

if TYPE_CHECKING:
    from granite.camera import CameraModel

#: The radial-tangential camera type (Basalt's name), undistorted to a pinhole camera on read.
RADTAN = "pinhole-radtan8"
#: Required intrinsic parameter names per camera type, in Basalt's order.
CAMERA_PARAMS: dict[str, tuple[str, ...]] = {
    "pinhole": ("fx", "fy", "cx", "cy"),
    "kb4": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "ds": ("fx", "fy", "cx", "cy", "xi", "alpha"),
    RADTAN: ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
#: Optional intrinsic parameters per camera type and their defaults.
OPTIONAL_PARAMS: dict[str, dict[str, float]] = {RADTAN: {"k3": 0.0, "k4": 0.0, "k5": 0.0, "k6": 0.0}}


@dataclass(frozen=True, eq=False)
class Calibration:
    """One camera: model, intrinsics (Basalt names), image size and ``T_imu_cam``."""

    camera_type: str
    intrinsics: dict[str, float]
    width: int
    height: int
    T_imu_cam: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        if self.camera_type not in CAMERA_PARAMS:
            raise ValueError(
                f"unknown camera_type {self.camera_type!r}; expected one of {sorted(CAMERA_PARAMS)}"
            )
        missing = [k for k in CAMERA_PARAMS[self.camera_type] if k not in self.intrinsics]
        if missing:
            raise ValueError(f"{self.camera_type} intrinsics lack {missing}")
        params = {k: float(self.intrinsics[k]) for k in CAMERA_PARAMS[self.camera_type]}
        for k, default in OPTIONAL_PARAMS.get(self.camera_type, {}).items():
            params[k] = float(self.intrinsics.get(k, default))
        if not all(math.isfinite(v) for v in params.values()):
            raise ValueError("intrinsics must be finite")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError("width and height must be positive")
        T = np.array(self.T_imu_cam, dtype=np.float64, copy=True)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("T_imu_cam must be a finite 4x4 matrix")
        T.setflags(write=False)
        object.__setattr__(self, "intrinsics", params)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "T_imu_cam", T)

    def camera(self) -> CameraModel:
        """The camera model object (:func:`granite.camera.make_camera`; raises
        :class:`granite.errors.ConfigError` for parameters outside the model's range, and for
        a ``pinhole-radtan8`` calibration, whose images the dataset undistorts: use
        :attr:`granite.io.Dataset.calibration`, the pinhole camera of those images)."""
        from granite.camera import make_camera

        if self.camera_type == RADTAN:
            raise ConfigError(f"camera type {RADTAN} is not a VO camera model: its images are "
                              "undistorted to a pinhole camera when a dataset reads them")
        return make_camera(self.camera_type, dict(self.intrinsics), self.width, self.height)

    def to_json_dict(self) -> dict[str, Any]:
        """Basalt's JSON structure (IMU fields filled with neutral defaults)."""
        (p,), (q,) = pq_from_poses(self.T_imu_cam[None])
        return {
            "value0": {
                "T_imu_cam": [
                    {
                        "px": float(p[0]), "py": float(p[1]), "pz": float(p[2]),
                        "qx": float(q[0]), "qy": float(q[1]), "qz": float(q[2]), "qw": float(q[3]),
                    }
                ],
                "intrinsics": [
                    {"camera_type": self.camera_type, "intrinsics": dict(self.intrinsics)}
                ],
                "resolution": [[self.width, self.height]],
                "vignette": [],
                "calib_accel_bias": [0.0] * 9,
                "calib_gyro_bias": [0.0] * 12,
                "imu_update_rate": 200.0,
                "accel_noise_std": [0.0, 0.0, 0.0],
                "gyro_noise_std": [0.0, 0.0, 0.0],
                "accel_bias_std": [0.0, 0.0, 0.0],
                "gyro_bias_std": [0.0, 0.0, 0.0],
                "cam_time_offset_ns": 0,
            }
        }


def _get(node: Any, key: str | int, jpath: str, p: Path) -> Any:
    """``node[key]`` or InputError naming the JSON path."""
    where = f"{jpath}[{key}]" if isinstance(key, int) else f"{jpath}.{key}"
    try:
        if isinstance(key, int):
            if not isinstance(node, list):
                raise InputError(f"{jpath} must be a list", p)
        elif not isinstance(node, dict):
            raise InputError(f"{jpath} must be an object", p)
        return node[key]
    except (KeyError, IndexError):
        raise InputError(f"missing field {where}", p) from None


def _number(value: Any, jpath: str, p: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{jpath} must be a finite number, got {value!r}", p)
    return float(value)


def parse_calibration(data: Any, path: str | Path) -> Calibration:
    """Calibration from decoded Basalt JSON ``data`` (``path`` for messages)."""
    p = Path(path)
    if not isinstance(data, dict):
        raise InputError("top level must be a JSON object", p)
    root = _get(data, "value0", "", p)
    cam = _get(_get(root, "intrinsics", "value0", p), 0, "value0.intrinsics", p)
    jcam = "value0.intrinsics[0]"
    ctype = _get(cam, "camera_type", jcam, p)
    if ctype not in CAMERA_PARAMS:
        raise InputError(
            f"{jcam}.camera_type: unsupported {ctype!r}; expected one of "
            f"{', '.join(sorted(CAMERA_PARAMS))}",
            p,
        )
    params = _get(cam, "intrinsics", jcam, p)
    intrinsics = {
        name: _number(_get(params, name, f"{jcam}.intrinsics", p), f"{jcam}.intrinsics.{name}", p)
        for name in CAMERA_PARAMS[ctype]
    }
    for name in OPTIONAL_PARAMS.get(ctype, {}):
        if isinstance(params, dict) and name in params:
            intrinsics[name] = _number(params[name], f"{jcam}.intrinsics.{name}", p)
    res = _get(_get(root, "resolution", "value0", p), 0, "value0.resolution", p)
    if (
        not isinstance(res, list)
        or len(res) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in res)
    ):
        raise InputError(f"value0.resolution[0] must be [width, height], got {res!r}", p)
    T_imu_cam = np.eye(4)
    if isinstance(root, dict) and root.get("T_imu_cam"):
        node = _get(root["T_imu_cam"], 0, "value0.T_imu_cam", p)
        jt = "value0.T_imu_cam[0]"
        keys = ("px", "py", "pz", "qx", "qy", "qz", "qw")
        v = {k: _number(_get(node, k, jt, p), f"{jt}.{k}", p) for k in keys}
        q = np.array([v["qx"], v["qy"], v["qz"], v["qw"]])
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise InputError(f"{jt}: quaternion norm {norm:.6g} is not 1", p)
        T_imu_cam = pose_from_pq(np.array([v["px"], v["py"], v["pz"]]), q / norm)
    try:
        calib = Calibration(ctype, intrinsics, res[0], res[1], T_imu_cam)
        if ctype == RADTAN:  # valid when a pinhole view of it exists
            from granite.io.undistortion import pinhole_view

            pinhole_view(calib)
        else:
            calib.camera()  # the camera model validates parameter ranges
    except (ValueError, ConfigError) as error:
        raise InputError(f"{jcam}: {error}", p) from None
    return calib


def read_calibration(path: str | Path) -> Calibration:
    """Read a Basalt calibration JSON; a missing field names its JSON path and the file."""
    p = Path(path)
    text = read_text(p, "calibration file")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        message = f"invalid JSON: {error.msg} (column {error.colno})"
        raise InputError(message, p, error.lineno) from None
    return parse_calibration(data, p)


def write_calibration(path: str | Path, calib: Calibration) -> None:
    """Atomically write ``calib`` as Basalt JSON."""
    atomic_write_text(path, json.dumps(calib.to_json_dict(), indent=4) + "\n")
