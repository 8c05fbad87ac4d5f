"""Images of a radial-tangential camera undistorted to a pinhole camera (OpenCV).

The VO's camera models are Basalt's (pinhole, ``kb4``, ``ds``). The radial-tangential model
(Basalt ``pinhole-radtan8``, OpenCV's rational model; EuRoC's ``radial-tangential`` with
``[k1, k2, p1, p2]``, ROS ``plumb_bob``) is handled once, where the images are read: every image
is remapped to a pinhole camera with the same size, and the VO, the evaluation and the
visualisation only see that pinhole camera. Camera frame and poses are unchanged (no
rectifying rotation), so ground truth and ``T_imu_cam`` still apply.

The pinhole intrinsics are OpenCV's ``getOptimalNewCameraMatrix`` with ``alpha = 0``: the
largest view in which every pixel comes from inside the distorted image (no black border,
whose edge would give the corner detector false corners). The maps are fixed-point
(``CV_16SC2``) and the interpolation bilinear, as in ``cv2.undistort``; deterministic.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from granite.io.calibration import RADTAN, Calibration


def _matrices(source: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's camera matrix and 8 distortion coefficients of a radial-tangential camera."""
    if source.camera_type != RADTAN:
        raise ValueError(f"camera type {source.camera_type!r} needs no undistortion")
    p = source.intrinsics
    if not (p["fx"] > 0.0 and p["fy"] > 0.0):
        raise ValueError("fx and fy must be positive")
    K = np.array([[p["fx"], 0.0, p["cx"]], [0.0, p["fy"], p["cy"]], [0.0, 0.0, 1.0]])
    return K, np.array([p[k] for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")])


def pinhole_view(source: Calibration) -> Calibration:
    """The pinhole camera (same size and ``T_imu_cam``) that a radial-tangential camera's
    images are undistorted to: ``getOptimalNewCameraMatrix`` with ``alpha = 0``. Raises
    ``ValueError`` when no valid view exists (coefficients so strong that the distortion folds
    over inside the image)."""
    K, D = _matrices(source)
    size = (source.width, source.height)
    K_new, _ = cv2.getOptimalNewCameraMatrix(K, D, size, 0.0, size, centerPrincipalPoint=False)
    fx, fy, cx, cy = K_new[0, 0], K_new[1, 1], K_new[0, 2], K_new[1, 2]
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0.0 or fy <= 0.0:
        raise ValueError("the radial-tangential coefficients leave no valid undistorted view")
    return Calibration("pinhole", {"fx": fx, "fy": fy, "cx": cx, "cy": cy},
                       source.width, source.height, source.T_imu_cam)


class Undistortion:
    """The remapping of one radial-tangential calibration (``source``, camera type
    :data:`~granite.io.calibration.RADTAN`) to its :func:`pinhole_view` (``target``); raises
    ``ValueError`` as that does."""

    def __init__(self, source: Calibration):
        self.source = source
        self.target = pinhole_view(source)
        K, D = _matrices(source)
        q = self.target.intrinsics
        K_new = np.array([[q["fx"], 0.0, q["cx"]], [0.0, q["fy"], q["cy"]], [0.0, 0.0, 1.0]])
        self._maps = cv2.initUndistortRectifyMap(K, D, None, K_new, (source.width, source.height),
                                                 cv2.CV_16SC2)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """The image in the pinhole camera. An image of another size than the calibration's is
        returned unchanged (the frontend rejects it as of the wrong size)."""
        if image.shape[:2] != (self.source.height, self.source.width):
            return image
        return cv2.remap(image, self._maps[0], self._maps[1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

    def describe(self) -> str:
        """One line for the dataset's notes."""
        p, q = self.source.intrinsics, self.target.intrinsics
        coeffs = ", ".join(f"{k} {p[k]:.6g}" for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
                           if p[k] != 0.0)
        return (f"images undistorted from radial-tangential ({coeffs}) to pinhole fx {q['fx']:.2f} "
                f"fy {q['fy']:.2f} cx {q['cx']:.2f} cy {q['cy']:.2f}")
