"""Reading a trajectory file whose format (TUM or EuRoC ground-truth CSV) is detected from
its content: if the first non-comment line has 8 or more comma-separated fields it is an
EuRoC CSV (nanoseconds, p xyz, q wxyz), otherwise a TUM file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from granite.io._text import data_lines, read_text
from granite.io.euroc import read_euroc_groundtruth
from granite.io.tum import parse_tum
from granite.trajectory import Trajectory


def detect_trajectory_format(text: str) -> str:
    """``"euroc"`` or ``"tum"`` from the first non-comment line of ``text``."""
    for _, line in data_lines(text):
        return "euroc" if len(line.split(",")) >= 8 else "tum"
    return "tum"


def read_trajectory(path: str | Path, T_body_cam: np.ndarray | None = None) -> Trajectory:
    """Read a TUM file or an EuRoC ground-truth CSV (auto-detected).

    ``T_body_cam`` is applied to EuRoC body poses only (``T_w_c = T_w_body @ T_body_cam``);
    TUM files already hold the poses they name.
    """
    text = read_text(path, "trajectory file")
    if detect_trajectory_format(text) == "euroc":
        return read_euroc_groundtruth(path, T_body_cam)
    return parse_tum(text, path)
