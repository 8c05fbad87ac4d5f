"""EuRoC / ASL dataset files.

* ``mav0/cam0/data.csv``: ``#timestamp [ns],filename`` (images in ``mav0/cam0/data/``).
* ``mav0/cam0/sensor.yaml``: ``T_BS`` (4x4 body-from-sensor = ``T_imu_cam``), ``resolution``
  ``[w, h]``, ``camera_model``, ``intrinsics [fu, fv, cu, cv]``, ``distortion_model`` and
  ``distortion_coefficients``. Parsed by a small parser for exactly this layout (no PyYAML).
* ``mav0/state_groundtruth_estimate0/data.csv``: ``timestamp [ns], p xyz [m], q wxyz, ...``
  (>= 8 comma-separated columns) = body (IMU) poses ``T_w_body``.

Timestamps are int64 nanoseconds in the files and float64 seconds in memory.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io._poses import poses_from_pq, pq_from_poses
from granite.io._text import (
    check_increasing,
    data_lines,
    normalise_quaternion,
    parse_float,
    parse_int,
    read_text,
    split_fields,
)
from granite.io.atomic import atomic_write_text
from granite.trajectory import Trajectory

GROUNDTRUTH_HEADER = (
    "#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], "
    "q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
)
IMAGE_LIST_HEADER = "#timestamp [ns],filename"
_GT_NAMES = ("timestamp", "p_x", "p_y", "p_z", "q_w", "q_x", "q_y", "q_z")


# --------------------------------------------------------------------------- time


def seconds_from_ns(ns: np.ndarray | int) -> np.ndarray:
    """float64 seconds from int64 nanoseconds (split into whole seconds and remainder to
    keep the rounding to one float64 ulp)."""
    ns = np.asarray(ns, dtype=np.int64)
    return (ns // 1_000_000_000).astype(np.float64) + (ns % 1_000_000_000) * 1e-9


def ns_from_seconds(seconds: np.ndarray | float) -> np.ndarray:
    """int64 nanoseconds (rounded) from float64 seconds."""
    s = np.asarray(seconds, dtype=np.float64)
    whole = np.floor(s)
    return whole.astype(np.int64) * 1_000_000_000 + np.round((s - whole) * 1e9).astype(np.int64)


def _is_text_header(number: int, fields: list[str]) -> bool:
    """A first line like ``timestamp,filename`` written without the leading ``#``."""
    return number == 1 and bool(fields) and bool(re.match(r"[A-Za-z_]", fields[0]))


# --------------------------------------------------------------------------- image list


def read_euroc_image_list(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """``(timestamps_ns int64 (N,), filenames)`` from a camera ``data.csv``."""
    p = Path(path)
    stamps: list[int] = []
    names: list[str] = []
    lines: list[int] = []
    for number, line in data_lines(read_text(p, "image list")):
        fields = split_fields(line, comma=True)
        if _is_text_header(number, fields):
            continue
        if len(fields) != 2:
            raise InputError(
                f"expected 2 columns (timestamp [ns], filename), got {len(fields)}", p, number
            )
        stamps.append(parse_int(fields[0], p, number, "timestamp [ns]"))
        if not fields[1]:
            raise InputError("empty filename", p, number)
        names.append(fields[1])
        lines.append(number)
    if not stamps:
        raise InputError("no images listed", p)
    check_increasing(stamps, lines, p)
    return np.array(stamps, dtype=np.int64), names


def write_euroc_image_list(
    path: str | Path, timestamps_ns: np.ndarray, filenames: list[str]
) -> None:
    """Atomically write a camera ``data.csv``."""
    stamps = np.asarray(timestamps_ns, dtype=np.int64)
    if stamps.shape != (len(filenames),):
        raise ValueError("timestamps_ns and filenames must have the same length")
    rows = [IMAGE_LIST_HEADER] + [f"{int(t)},{name}" for t, name in zip(stamps, filenames)]
    atomic_write_text(path, "\n".join(rows) + "\n")


# --------------------------------------------------------------------------- ground truth


def read_euroc_groundtruth(
    path: str | Path, T_body_cam: np.ndarray | None = None
) -> Trajectory:
    """Camera poses ``T_w_c = T_w_body @ T_body_cam`` from an EuRoC ground-truth CSV.

    Columns after the 8th (velocities, biases) are validated as numbers and ignored.
    ``T_body_cam`` defaults to the identity (the trajectory of the body frame itself).
    """
    p = Path(path)
    times: list[float] = []
    pos: list[list[float]] = []
    quats: list[np.ndarray] = []
    lines: list[int] = []
    ncols = 0
    for number, line in data_lines(read_text(p, "ground-truth file")):
        fields = split_fields(line, comma=True)
        if _is_text_header(number, fields):
            continue
        if ncols == 0:
            if len(fields) < 8:
                raise InputError(
                    "expected at least 8 comma-separated columns "
                    f"(timestamp [ns], p xyz, q wxyz), got {len(fields)}",
                    p,
                    number,
                )
            ncols = len(fields)
        elif len(fields) != ncols:
            raise InputError(
                f"expected {ncols} columns like the first row, got {len(fields)}", p, number
            )
        stamp = parse_int(fields[0], p, number, "timestamp [ns]")
        values = [parse_float(f, p, number, n) for f, n in zip(fields[1:8], _GT_NAMES[1:])]
        for k, extra in enumerate(fields[8:], start=9):
            parse_float(extra, p, number, f"column {k}")
        times.append(stamp)
        pos.append(values[0:3])
        qw, qx, qy, qz = normalise_quaternion(values[3:7], p, number)
        quats.append(np.array([qx, qy, qz, qw]))
        lines.append(number)
    if not times:
        raise InputError("empty trajectory: no pose rows", p)
    check_increasing(times, lines, p)
    poses = poses_from_pq(np.array(pos), np.array(quats))
    if T_body_cam is not None:
        poses = poses @ np.asarray(T_body_cam, dtype=np.float64)
    return Trajectory(seconds_from_ns(np.array(times, dtype=np.int64)), poses)


def write_euroc_groundtruth(path: str | Path, traj: Trajectory) -> None:
    """Atomically write ``traj`` as an 8-column EuRoC ground-truth CSV (ns, p xyz, q wxyz).

    Sub-map indices are not stored. Timestamps are rounded to whole nanoseconds.
    """
    positions, quats = pq_from_poses(traj.poses)
    stamps = ns_from_seconds(traj.timestamps)
    if len(stamps) > 1 and not np.all(np.diff(stamps) > 0):
        raise ValueError("timestamps closer than 1 ns cannot be written in EuRoC format")
    rows = [GROUNDTRUTH_HEADER]
    for i in range(len(traj)):
        x, y, z = positions[i]
        qx, qy, qz, qw = quats[i]
        values = [repr(float(v)) for v in (x, y, z, qw, qx, qy, qz)]
        rows.append(",".join([str(int(stamps[i])), *values]))
    atomic_write_text(path, "\n".join(rows) + "\n")


# --------------------------------------------------------------------------- sensor.yaml


@dataclass(frozen=True, eq=False)
class SensorInfo:
    """The camera fields of an EuRoC ``sensor.yaml`` (missing fields are ``None``)."""

    T_BS: np.ndarray | None
    resolution: tuple[int, int] | None
    camera_model: str | None
    intrinsics: list[float] | None
    distortion_model: str | None
    distortion_coefficients: list[float] = field(default_factory=list)


def _yaml_blocks(text: str) -> dict[str, tuple[int, str]]:
    """Top-level ``key: value`` blocks: key -> (line, value text with continuation lines)."""
    blocks: dict[str, tuple[int, str]] = {}
    key = None
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip()
        if not line.strip():
            continue
        m = re.match(r"([A-Za-z_][\w-]*)\s*:(.*)$", line)
        if m and not raw[0].isspace():
            key = m.group(1)
            blocks[key] = (number, m.group(2).strip())
        elif key is not None:
            start, value = blocks[key]
            blocks[key] = (start, f"{value} {line.strip()}")
    return blocks


def _yaml_numbers(value: str, p: Path, line: int, key: str) -> list[float]:
    m = re.search(r"\[(.*)\]", value)
    if not m:
        raise InputError(f"{key}: expected a list [a, b, ...], got {value!r}", p, line)
    items = [s.strip() for s in m.group(1).split(",") if s.strip()]
    return [parse_float(s, p, line, key) for s in items]


def read_sensor_yaml(path: str | Path) -> SensorInfo:
    """Parse the camera fields of an EuRoC ``sensor.yaml``."""
    p = Path(path)
    blocks = _yaml_blocks(read_text(p, "sensor file"))
    T_BS = None
    if "T_BS" in blocks:
        line, value = blocks["T_BS"]
        m = re.search(r"data\s*:\s*(\[.*?\])", value)
        if not m:
            raise InputError("T_BS: no 'data: [...]' list", p, line)
        data = _yaml_numbers(m.group(1), p, line, "T_BS.data")
        if len(data) not in (12, 16):
            raise InputError(f"T_BS.data: expected 16 numbers, got {len(data)}", p, line)
        T_BS = np.eye(4)
        T_BS[: len(data) // 4] = np.reshape(data, (-1, 4))
    resolution = None
    if "resolution" in blocks:
        line, value = blocks["resolution"]
        res = _yaml_numbers(value, p, line, "resolution")
        if len(res) != 2 or any(r <= 0 or r != int(r) for r in res):
            raise InputError(f"resolution: expected [width, height], got {value}", p, line)
        resolution = (int(res[0]), int(res[1]))

    def scalar(key: str) -> str | None:
        return blocks[key][1].strip("'\" ") or None if key in blocks else None

    def numbers(key: str) -> list[float] | None:
        return _yaml_numbers(blocks[key][1], p, blocks[key][0], key) if key in blocks else None

    return SensorInfo(
        T_BS=T_BS,
        resolution=resolution,
        camera_model=scalar("camera_model"),
        intrinsics=numbers("intrinsics"),
        distortion_model=scalar("distortion_model"),
        distortion_coefficients=numbers("distortion_coefficients") or [],
    )


def write_sensor_yaml(
    path: str | Path,
    T_BS: np.ndarray,
    resolution: tuple[int, int],
    intrinsics: list[float],
    camera_model: str = "pinhole",
    distortion_model: str = "radial-tangential",
    distortion_coefficients: list[float] | None = None,
    rate_hz: float | None = None,
) -> None:
    """Atomically write a camera ``sensor.yaml`` in the EuRoC layout."""
    dist = [0.0, 0.0, 0.0, 0.0] if distortion_coefficients is None else distortion_coefficients
    data = ", ".join(repr(float(v)) for v in np.asarray(T_BS, dtype=np.float64).ravel())
    lines = [
        "# General sensor definitions.",
        "sensor_type: camera",
        "comment: cam0",
        "",
        "# Sensor extrinsics wrt. the body-frame.",
        "T_BS:",
        "  cols: 4",
        "  rows: 4",
        f"  data: [{data}]",
        "",
        "# Camera specific definitions.",
    ]
    if rate_hz is not None:
        lines.append(f"rate_hz: {rate_hz!r}")
    lines += [
        f"resolution: [{int(resolution[0])}, {int(resolution[1])}]",
        f"camera_model: {camera_model}",
        f"intrinsics: [{', '.join(repr(float(v)) for v in intrinsics)}]",
        f"distortion_model: {distortion_model}",
        f"distortion_coefficients: [{', '.join(repr(float(v)) for v in dist)}]",
    ]
    atomic_write_text(path, "\n".join(lines) + "\n")
