"""Per-frame diagnostics of a VO run and their CSV form.

One row per processed frame (skipped frames included). Columns:

=====================  =====================================================================
``timestamp``          frame time, seconds
``frame_index``        index of the frame in the dataset
``submap``             sub-map index (increments after every restart, and after a
                       re-initialisation that does not keep the scale)
``state``              ``skipped`` (image missing/corrupt, or rejected by the frontend: no
                       pose, not in ``trajectory.tum``), ``init`` (no map yet, rotation-only
                       tracking), ``tracking``, ``reinit`` (the map, lost with every point at
                       infinity, was initialised again in this frame), ``lost`` (tracking
                       failure: restart follows)
``tracked_points``     optical-flow tracks in this frame
``finite_landmarks``   connected landmarks with inverse distance > 0
``infinite_landmarks`` connected landmarks at infinity (d = 0)
``keyframe``           1 when this frame became a keyframe (decided one frame later, Sec. IV-D)
``negative_entropy``   ln det of the pose information (Eq. 10); empty when not computed
``processing_ms``      wall-clock time spent on this frame by the estimator's thread (in the
                       concurrent pipeline without Λ_scaledrift, computed beside the next frame)
``warnings``           Python warnings (e.g. numpy's RuntimeWarning) raised while processing
                       it; each kind is listed once in ``summary.json``
``scale_drift_indicator``      Λ_scaledrift of paper Eq. 17 at this frame's final estimate
                       (:mod:`granite.backend.scale_drift`); empty when not defined (fewer than
                       3 keyframes, no scale anchor, not tracking)
``scale_drift_indicator_ref``  the released reference code's variant of Λ (eigenvector-weighted
                       translations); empty when not defined
``scale_drift_reason`` why Λ is empty on a frame where it was computed: fewer than 3
                       keyframes, no scale anchor (nothing fixes the window's scale), no scale
                       across a keyframe link (no landmark seen in three keyframes across it:
                       the scale drift is unbounded there), non-finite or indefinite
                       information; empty when Λ is defined or was not computed
``gn_iterations``      Gauss-Newton (or Levenberg-Marquardt) iterations spent on this frame:
                       its main optimisation, a new keyframe's extra iterations and the
                       re-optimisation after outlier removal
``gn_converged``       1 when the frame's main optimisation stopped by its step rule, 0 when it
                       used all ``[backend] max_iterations`` (or LM stalled); empty when none ran
=====================  =====================================================================

Unavailable values are written as empty fields, never as NaN. Reading derives the columns and
their types from :class:`FrameDiagnostics`: a new field needs nothing else; files written
before a field with a default existed read with that default.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import MISSING, astuple, dataclass, fields
from pathlib import Path

from granite.backend.scale_drift import NO_SCALE_ANCHOR, NO_SCALE_LINK
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
    warnings: int = 0
    scale_drift_indicator: float | None = None
    scale_drift_indicator_ref: float | None = None
    scale_drift_reason: str = ""
    gn_iterations: int = 0
    gn_converged: bool | None = None

    @property
    def no_scale_information(self) -> bool:
        """Λ found no scale information in the window (no anchor, or a keyframe link that
        carries none): the scale drift is unbounded on this frame."""
        return self.scale_drift_reason in (NO_SCALE_ANCHOR, NO_SCALE_LINK)


COLUMNS = tuple(f.name for f in fields(FrameDiagnostics))
#: Columns every diagnostics file has (the fields without a default).
REQUIRED_COLUMNS = tuple(f.name for f in fields(FrameDiagnostics)
                         if f.default is MISSING and f.default_factory is MISSING)


def csv_cell(value) -> str:
    """A CSV cell: empty for None and non-finite floats (never NaN), 1/0 for booleans, floats
    with full precision."""
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
        values = [csv_cell(v) for v in astuple(row)]
        values[0] = f"{row.timestamp:.9f}"  # nanosecond resolution, no float noise
        writer.writerow(values)
    return buffer.getvalue()


def write_diagnostics(path: str | Path, rows: list[FrameDiagnostics]) -> None:
    """Write the diagnostics CSV atomically."""
    atomic_write_text(path, diagnostics_to_csv(rows))


def _parse_bool(text: str) -> bool:
    if text not in ("0", "1"):
        raise ValueError(f"expected 0 or 1, got {text!r}")
    return text == "1"


def _parser(annotation: str):
    """Text -> value for a field annotation (``X | None``: empty text gives None)."""
    base = annotation.replace("| None", "").replace("None |", "").strip()
    convert = {"bool": _parse_bool, "float": float, "int": int, "str": str}[base]
    if "None" in annotation:
        return lambda text: convert(text) if text != "" else None
    return convert


def read_diagnostics(path: str | Path) -> list[FrameDiagnostics]:
    """Read a diagnostics CSV written by :func:`write_diagnostics` (any version: columns are
    matched by name; missing optional columns take their default)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("diagnostics file not found", path)
    parsers = {f.name: _parser(str(f.type)) for f in fields(FrameDiagnostics)}
    rows: list[FrameDiagnostics] = []
    with path.open(newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None:
            raise InputError("empty diagnostics file", path)
        unknown = [c for c in header if c not in parsers]
        missing = [c for c in REQUIRED_COLUMNS if c not in header]
        if unknown or missing or len(set(header)) != len(header):
            problem = (f"unknown column(s) {', '.join(unknown)}" if unknown else
                       f"missing column(s) {', '.join(missing)}" if missing else "repeated columns")
            raise InputError(f"not a diagnostics header ({problem}); expected {','.join(COLUMNS)}", path, 1)
        for line, values in enumerate(reader, start=2):
            if len(values) != len(header):
                raise InputError(f"expected {len(header)} fields, got {len(values)}", path, line)
            try:
                kwargs = {name: parsers[name](text) for name, text in zip(header, values)}
            except (ValueError, KeyError) as error:
                raise InputError(f"malformed row ({error})", path, line) from None
            if kwargs["state"] not in FRAME_STATES:
                raise InputError(f"unknown state {kwargs['state']!r}", path, line)
            rows.append(FrameDiagnostics(**kwargs))
    return rows


def diagnostics_columns(rows: list[FrameDiagnostics]) -> dict[str, list]:
    """Column name -> values (``None`` where unavailable), for plotting."""
    return {name: [getattr(r, name) for r in rows] for name in COLUMNS}
