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


def default_flight(n: int, rate: float = 20.0):
    """Timestamps and poses of a smooth oblique flight over the plane (about 2 m/s, 10 m up)."""
    ts = np.arange(n) / rate
    poses = np.array(
        [look_down_pose([2.0 * t, 0.5 * np.sin(t), 10.0 + 0.5 * t], yaw=0.1 * t, pitch_deg=15) for t in ts]
    )
    return ts, poses


def write_planar_dataset(root, timestamps, poses, size=(320, 240), focal=200.0, seed=0, images=None):
    """Write a test-bench-style dataset (EuRoC layout, calib.json, groundtruth.tum) of the
    textured plane seen from ``poses``; ``images`` may replace individual images (index->array
    or None to omit the image file but keep its row)."""
    from pathlib import Path

    from granite.io import Calibration, write_calibration, write_euroc_image_list, write_tum
    from granite.trajectory import Trajectory

    root = Path(root)
    data = root / "mav0" / "cam0" / "data"
    data.mkdir(parents=True, exist_ok=True)
    w, h = size
    K = np.array([[focal, 0, (w - 1) / 2], [0, focal, (h - 1) / 2], [0, 0, 1.0]])
    texture = make_texture(2048, seed)
    ns = np.round(np.asarray(timestamps) * 1e9).astype(np.int64) + 1_000_000_000
    names = []
    for i, (stamp, T) in enumerate(zip(ns, poses)):
        name = f"{stamp}.png"
        names.append(name)
        image = render_plane(texture, 0.02, T, K, (w, h))
        if images is not None and i in images:
            image = images[i]
            if image is None:
                continue
            if isinstance(image, bytes):
                (data / name).write_bytes(image)
                continue
        cv2.imwrite(str(data / name), image)
    write_euroc_image_list(root / "mav0" / "cam0" / "data.csv", ns, names)
    intr = {"fx": focal, "fy": focal, "cx": (w - 1) / 2, "cy": (h - 1) / 2}
    write_calibration(root / "calib.json", Calibration("pinhole", intr, w, h))
    write_tum(root / "groundtruth.tum", Trajectory(ns / 1e9, poses))
    return root
