"""TUM trajectory files: one pose per row ``t tx ty tz qx qy qz qw [submap]``.

``t`` in seconds, position in metres (or map units), Hamilton quaternion ``qx qy qz qw`` of
``T_w_c``. An optional 9th integer column is the sub-map index (granite extension; evo and
other tools accept only the 8-column form, which ``granite run`` writes). Rows are whitespace separated; ``#`` comment
lines and blank lines are skipped. All rows must have the same number of columns.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io._poses import poses_from_pq, pq_from_poses
from granite.io._text import (
    check_increasing,
    data_lines,
    format_float,
    normalise_quaternion,
    parse_row,
    read_text,
)
from granite.io.atomic import atomic_write_text
from granite.trajectory import Trajectory

_NAMES = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw", "submap")
HEADER = "# timestamp tx ty tz qx qy qz qw"


def parse_tum(text: str, path: str | Path) -> Trajectory:
    """Parse TUM ``text`` (``path`` is used in error messages)."""
    p = Path(path)
    times: list[float] = []
    pos: list[list[float]] = []
    quats: list[np.ndarray] = []
    submaps: list[int] = []
    lines: list[int] = []
    ncols = 0
    for number, line in data_lines(text):
        fields = line.split()
        if ncols == 0:
            if len(fields) not in (8, 9):
                raise InputError(
                    f"expected 8 columns (t tx ty tz qx qy qz qw) or 9 (+ submap), "
                    f"got {len(fields)}",
                    p,
                    number,
                )
            ncols = len(fields)
        elif len(fields) != ncols:
            raise InputError(
                f"expected {ncols} columns like the first row, got {len(fields)}", p, number
            )
        values = parse_row(fields, _NAMES, p, number)
        times.append(values[0])
        pos.append(values[1:4])
        quats.append(normalise_quaternion(values[4:8], p, number))
        if ncols == 9:
            if values[8] != round(values[8]):
                raise InputError(f"submap: {fields[8]!r} is not an integer", p, number)
            submaps.append(int(values[8]))
        lines.append(number)
    if not times:
        raise InputError("empty trajectory: no pose rows", p)
    check_increasing(times, lines, p)
    poses = poses_from_pq(np.array(pos), np.array(quats))
    submap = np.array(submaps, dtype=np.int64) if ncols == 9 else None
    return Trajectory(np.array(times), poses, submap)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file (8 columns, or 9 with the sub-map index)."""
    return parse_tum(read_text(path, "trajectory file"), path)


def format_tum(traj: Trajectory, header: bool = True, submap_column: bool = True) -> str:
    """TUM text of ``traj`` at full float precision; a 9th column when ``traj.submap`` is set
    and ``submap_column`` is true (``False``: the plain 8-column form that evo reads)."""
    positions, quats = pq_from_poses(traj.poses)
    with_submap = submap_column and traj.submap is not None
    rows = [HEADER + (" submap" if with_submap else "")] if header else []
    for i in range(len(traj)):
        values = [traj.timestamps[i], *positions[i], *quats[i]]
        row = " ".join(format_float(v) for v in values)
        if with_submap:
            row += f" {int(traj.submap[i])}"
        rows.append(row)
    return "\n".join(rows) + "\n"


def write_tum(path: str | Path, traj: Trajectory, header: bool = True, submap_column: bool = True) -> None:
    """Atomically write ``traj`` as a TUM file (see :func:`format_tum`)."""
    atomic_write_text(path, format_tum(traj, header, submap_column))
