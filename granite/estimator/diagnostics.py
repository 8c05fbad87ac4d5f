"""Per-frame diagnostics of a VO run and their CSV form.

One row per processed frame (skipped frames included). Columns:

=====================  =====================================================================
``timestamp``          frame time, seconds
``frame_index``        index of the frame in the dataset
``submap``             sub-map index (increments after every restart)
``state``              ``skipped`` (image missing/corrupt), ``init`` (no map yet, rotation-only
                       tracking), ``tracking``, ``reinit`` (the map, lost with every point at
                       infinity, was initialised again in this frame; same sub-map),
                       ``lost`` (tracking failure: restart follows)
``tracked_points``     optical-flow tracks in this frame
``finite_landmarks``   connected landmarks with inverse distance > 0
``infinite_landmarks`` connected landmarks at infinity (d = 0)
``keyframe``           1 when this frame became a keyframe (decided one frame later, Sec. IV-D)
``negative_entropy``   ln det of the pose information (Eq. 10); empty when not computed
``processing_ms``      wall-clock time spent on this frame
=====================  =====================================================================

Unavailable values are written as empty fields, never as NaN.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import astuple, dataclass, fields
from pathlib import Path

from granite.errors import InputError
from granite.io import atomic_write_text

FRAME_STATES = ("skipped", "init", "tracking", "reinit", "lost")


@dataclass
class FrameDiagnostics:
    timestamp: float
    frame_index: int
    submap: int
    state: str
    tracked_points: int = 0
    finite_landmarks: int = 0
    infinite_landmarks: int = 0
    keyframe: bool = False
    negative_entropy: float | None = None
    processing_ms: float = 0.0


COLUMNS = tuple(f.name for f in fields(FrameDiagnostics))


def _format(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return "" if not math.isfinite(value) else repr(value)
    return str(value)


def diagnostics_to_csv(rows: list[FrameDiagnostics]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        values = [_format(v) for v in astuple(row)]
        values[0] = f"{row.timestamp:.9f}"  # nanosecond resolution, no float noise
        writer.writerow(values)
    return buffer.getvalue()


def write_diagnostics(path: str | Path, rows: list[FrameDiagnostics]) -> None:
    """Write the diagnostics CSV atomically."""
    atomic_write_text(path, diagnostics_to_csv(rows))


def read_diagnostics(path: str | Path) -> list[FrameDiagnostics]:
    """Read a diagnostics CSV written by :func:`write_diagnostics`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("diagnostics file not found", path)
    rows: list[FrameDiagnostics] = []
    with path.open(newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None or tuple(header) != COLUMNS:
            raise InputError(f"expected the header {','.join(COLUMNS)}", path, 1)
        for line, values in enumerate(reader, start=2):
            try:
                t, idx, sub, state, tracked, fin, inf, kf, ent, ms = values
                rows.append(
                    FrameDiagnostics(
                        float(t), int(idx), int(sub), state, int(tracked), int(fin), int(inf),
                        kf == "1", float(ent) if ent else None, float(ms),
                    )
                )
            except ValueError as error:
                raise InputError(f"malformed row ({error})", path, line) from None
            if state not in FRAME_STATES:
                raise InputError(f"unknown state {state!r}", path, line)
    return rows
