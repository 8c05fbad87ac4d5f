"""Exact synthetic images of a textured ground plane (z = 0, world z up), without Blender.

A camera ``T_w_c`` (CV convention) sees the plane through the homography
``x ~ K [r1 r2 t]_c_w A u`` where ``A`` maps texture pixels ``u`` to plane coordinates. Used by
tests that need image sequences with exact ground truth and known depth.
"""

from __future__ import annotations

import cv2
import numpy as np

from granite.geometry import se3_inverse


def make_texture(size: int = 2048, seed: int = 0) -> np.ndarray:
    """Multi-scale random texture (uint8), deterministic."""
    rng = np.random.default_rng(seed)
    img = np.zeros((size, size), np.float32)
    for scale, amp in ((64, 1.0), (16, 0.8), (4, 0.6)):
        small = rng.random((size // scale + 2, size // scale + 2)).astype(np.float32)
        img += amp * cv2.resize(small, (size + 2 * scale, size + 2 * scale), interpolation=cv2.INTER_CUBIC)[
            scale : scale + size, scale : scale + size
        ]
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 235 + 10).astype(np.uint8)


def look_down_pose(position, yaw: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """Camera at ``position`` looking straight down (z forward = -world z), rotated by ``yaw``
    about the world z axis and tilted forward by ``pitch_deg``."""
    R_down = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # x right, y down in image
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    p = np.radians(pitch_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    T = np.eye(4)
    T[:3, :3] = Rz @ R_down @ Rx
    T[:3, 3] = position
    return T


def render_plane(texture: np.ndarray, metres_per_pixel: float, T_w_c: np.ndarray, K: np.ndarray, size) -> np.ndarray:
    """Image (uint8) of the textured plane; the texture's centre is the world origin."""
    n = texture.shape[0]
    A = np.array([[metres_per_pixel, 0, -metres_per_pixel * (n - 1) / 2],
                  [0, metres_per_pixel, -metres_per_pixel * (n - 1) / 2],
                  [0, 0, 1.0]])
    T_c_w = se3_inverse(T_w_c)
    H = K @ np.column_stack([T_c_w[:3, 0], T_c_w[:3, 1], T_c_w[:3, 3]]) @ A
    return cv2.warpPerspective(texture, H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
