"""TUM RGB-D dataset files: ``rgb.txt`` (``timestamp filename`` per row, filename relative
to the dataset folder, ``#`` comments) and ``groundtruth.txt`` (TUM trajectory of the colour
camera, read with :func:`granite.io.tum.read_tum`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from granite.errors import InputError
from granite.io._text import check_increasing, data_lines, parse_float, read_text


def read_tum_rgbd_list(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """``(timestamps [s] (N,), filenames)`` from ``rgb.txt``."""
    p = Path(path)
    times: list[float] = []
    names: list[str] = []
    lines: list[int] = []
    for number, line in data_lines(read_text(p, "image list")):
        fields = line.split()
        if len(fields) != 2:
            message = f"expected 2 columns (timestamp filename), got {len(fields)}"
            raise InputError(message, p, number)
        times.append(parse_float(fields[0], p, number, "timestamp"))
        names.append(fields[1])
        lines.append(number)
    if not times:
        raise InputError("no images listed", p)
    check_increasing(times, lines, p)
    return np.array(times), names
