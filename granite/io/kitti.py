"""KITTI odometry files.

A sequence folder ``sequences/XX`` holds ``image_0/NNNNNN.png`` (left grayscale camera; the
colour download has ``image_2`` / ``image_3`` instead), ``times.txt`` (one timestamp in seconds
per line) and ``calib.txt`` (``P0: p00 .. p23`` to ``P3``, the rectified 3x4 projection
matrices ``P_i = K_i [I | t_i]`` of the four cameras in camera 0's frame; pinhole ``fx = p00,
fy = p11, cx = p02, cy = p12``, and camera i sits at ``-t_i`` in camera 0's frame, ``t_i =
K_i^-1 P_i[:, 3]``). Ground truth ``poses/XX.txt`` (next to ``sequences/``): per image one row of
12 numbers, the row-major 3x4 ``T_w_c`` of camera 0 (world = first camera frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io._poses import orthonormalise
from granite.io._text import check_increasing, data_lines, format_float, parse_float, parse_row, read_text
from granite.io.atomic import atomic_write_text
from granite.trajectory import Trajectory


def read_kitti_times(path: str | Path) -> np.ndarray:
    """Timestamps in seconds from ``times.txt`` (one per line, strictly increasing)."""
    p = Path(path)
    times: list[float] = []
    lines: list[int] = []
    for number, line in data_lines(read_text(p, "times file")):
        fields = line.split()
        if len(fields) != 1:
            raise InputError(f"expected 1 column (timestamp [s]), got {len(fields)}", p, number)
        times.append(parse_float(fields[0], p, number, "timestamp"))
        lines.append(number)
    if not times:
        raise InputError("no timestamps", p)
    check_increasing(times, lines, p)
    return np.array(times)


def read_kitti_projection(path: str | Path, camera: int = 0) -> tuple[dict[str, float], np.ndarray]:
    """Pinhole ``{fx, fy, cx, cy}`` of camera ``camera`` (0-3) from its ``P<camera>:`` row of
    ``calib.txt``, and ``T_c0_ci`` (4, 4): that camera's pose in camera 0's frame (a
    translation: the rectified cameras share camera 0's orientation)."""
    p = Path(path)
    name = f"P{camera}"
    for number, line in data_lines(read_text(p, "calibration file")):
        key, _, rest = line.partition(":")
        if key.strip() != name:
            continue
        fields = rest.split()
        if len(fields) != 12:
            raise InputError(f"{name}: expected 12 numbers, got {len(fields)}", p, number)
        P = np.array(parse_row(fields, [f"{name}[{i}]" for i in range(12)], p, number)).reshape(3, 4)
        if P[0, 0] <= 0 or P[1, 1] <= 0:
            raise InputError(f"{name}: focal lengths must be positive", p, number)
        T_c0_ci = np.eye(4)
        T_c0_ci[:3, 3] = -np.linalg.solve(P[:, :3], P[:, 3])
        return {"fx": P[0, 0], "fy": P[1, 1], "cx": P[0, 2], "cy": P[1, 2]}, T_c0_ci
    raise InputError(f"no '{name}:' row", p)


def read_kitti_intrinsics(path: str | Path) -> dict[str, float]:
    """Pinhole ``{fx, fy, cx, cy}`` from the ``P0:`` row of ``calib.txt``."""
    return read_kitti_projection(path, 0)[0]


def read_kitti_poses(path: str | Path, timestamps: np.ndarray) -> Trajectory:
    """Ground truth ``T_w_c`` rows (12 numbers, row-major 3x4), one per timestamp.

    Rotations printed with few digits are re-orthonormalised (within 1e-3)."""
    p = Path(path)
    poses: list[np.ndarray] = []
    for number, line in data_lines(read_text(p, "poses file")):
        fields = line.split()
        if len(fields) != 12:
            message = f"expected 12 numbers (3x4 pose, row-major), got {len(fields)}"
            raise InputError(message, p, number)
        T = np.eye(4)
        T[:3] = np.array(parse_row(fields, [f"T[{i}]" for i in range(12)], p, number)).reshape(3, 4)
        R = orthonormalise(T[:3, :3])
        if R is None:
            raise InputError("the 3x3 rotation block is not a rotation matrix", p, number)
        T[:3, :3] = R
        poses.append(T)
    if not poses:
        raise InputError("empty trajectory: no pose rows", p)
    if len(poses) != len(timestamps):
        raise InputError(f"{len(poses)} poses but {len(timestamps)} timestamps in times.txt", p)
    return Trajectory(np.asarray(timestamps, dtype=np.float64), np.array(poses))


def format_kitti_poses(traj: Trajectory) -> str:
    """KITTI odometry pose text of ``traj``: per pose one row of 12 numbers, the row-major 3x4
    ``T_w_c`` (full float precision; no timestamps, no header)."""
    rows = [" ".join(format_float(v) for v in T[:3].reshape(-1)) for T in traj.poses]
    return "\n".join(rows) + ("\n" if rows else "")


def write_kitti_poses(path: str | Path, traj: Trajectory) -> None:
    """Atomically write ``traj`` as a KITTI odometry pose file (:func:`format_kitti_poses`)."""
    atomic_write_text(path, format_kitti_poses(traj))
