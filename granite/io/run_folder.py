"""Reading the trajectory of a ``granite run`` folder, with its sub-maps.

``trajectory.tum`` is plain 8-column TUM (what evo reads); the sub-map index of every pose is
in ``submaps.csv`` beside it (``timestamp,frame_index,submap``, one row per pose, same order).
Older run folders have the index as a 9th column of ``trajectory.tum``; both are read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io._text import data_lines, parse_float, read_text
from granite.io.trajectory_file import read_trajectory
from granite.trajectory import Trajectory

SUBMAPS_FILE = "submaps.csv"
SUBMAPS_HEADER = "timestamp,frame_index,submap"
#: Timestamps of a trajectory and its submaps.csv agree within this (s; the CSV has 9 decimals).
TIME_TOLERANCE = 1e-6


def read_submaps(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(timestamps [s], frame_indices, submaps)`` of a ``submaps.csv``."""
    p = Path(path)
    rows = list(data_lines(read_text(p, "sub-map file")))
    if not rows or rows[0][1].replace(" ", "") != SUBMAPS_HEADER:
        raise InputError(f"expected the header {SUBMAPS_HEADER}", p, rows[0][0] if rows else None)
    t, idx, sub = [], [], []
    for number, line in rows[1:]:
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 3:
            raise InputError(f"expected 3 fields ({SUBMAPS_HEADER}), got {len(fields)}", p, number)
        t.append(parse_float(fields[0], p, number, "timestamp"))
        for name, text, out in (("frame_index", fields[1], idx), ("submap", fields[2], sub)):
            try:
                out.append(int(text))
            except ValueError:
                raise InputError(f"{name}: {text!r} is not an integer", p, number) from None
    return np.array(t), np.array(idx, np.int64), np.array(sub, np.int64)


def attach_submaps(traj: Trajectory, path: str | Path) -> Trajectory:
    """``traj`` with the sub-map indices of ``submaps.csv`` at ``path`` (rows must match the
    poses one to one, same timestamps)."""
    t, _, sub = read_submaps(path)
    if len(t) != len(traj) or not np.allclose(t, traj.timestamps, rtol=0.0, atol=TIME_TOLERANCE):
        raise InputError(f"does not match the trajectory ({len(t)} rows for {len(traj)} poses, or other "
                         "timestamps); pass --submaps none to evaluate it as one sub-map", path)
    return Trajectory(traj.timestamps, traj.poses, sub)


def read_estimate(path: str | Path, submaps: str | Path | None = None) -> tuple[Trajectory, str]:
    """An estimated trajectory and where its sub-maps came from.

    ``path``: a TUM file (8 or 9 columns) or a run folder (its ``trajectory.tum``).
    ``submaps``: ``None`` = automatic (the 9th column, else a ``submaps.csv`` beside the
    file, else one sub-map), ``"none"`` = one sub-map, or the path of a ``submaps.csv``.
    The second value says which: ``"9th column"``, the CSV's path, or ``"none"``.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "trajectory.tum"
        if not p.is_file():
            raise InputError("a run folder needs a trajectory.tum", path)
    traj = read_trajectory(p)
    if submaps is not None and str(submaps) == "none":
        return Trajectory(traj.timestamps, traj.poses), "none"
    if submaps is not None:
        return attach_submaps(traj, submaps), str(submaps)
    if traj.submap is not None:
        return traj, "9th column"
    beside = p.parent / SUBMAPS_FILE
    if beside.is_file():
        return attach_submaps(traj, beside), str(beside)
    return traj, "none"
