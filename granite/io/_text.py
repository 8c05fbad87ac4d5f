"""Shared helpers for the line-based text formats: reading, row parsing, validation.

Line numbers are 1-based physical lines of the file, so error messages point at the line a
user has to fix.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from granite.errors import InputError

#: A quaternion whose norm differs from 1 by more than this is rejected, else normalised.
QUAT_NORM_TOL = 1e-3


def read_text(path: str | Path, what: str = "file") -> str:
    """The text of ``path``; a missing, unreadable or non-UTF-8 file raises InputError."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{what} not found", p)
    if p.is_dir():
        raise InputError(f"expected a {what}, found a directory", p)
    try:
        return p.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"not a text file ({error.reason} at byte {error.start})", p) from None
    except OSError as error:
        raise InputError(f"cannot read {what}: {error.strerror}", p) from None


def data_lines(text: str, comment: str = "#") -> Iterator[tuple[int, str]]:
    """``(line_number, stripped_line)`` of every non-blank, non-comment line."""
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith(comment):
            yield number, line


def split_fields(line: str, comma: bool) -> list[str]:
    """Fields of a row: comma separated (surrounding spaces ignored) or whitespace separated."""
    if comma:
        return [f.strip() for f in line.split(",")]
    return line.split()


def parse_float(field: str, path: Path, line: int, name: str) -> float:
    """A finite float, else InputError naming the column."""
    try:
        value = float(field)
    except ValueError:
        raise InputError(f"{name}: {field!r} is not a number", path, line) from None
    if not math.isfinite(value):
        raise InputError(f"{name}: {field!r} is not finite", path, line)
    return value


def parse_int(field: str, path: Path, line: int, name: str) -> int:
    """An integer (e.g. nanoseconds), else InputError naming the column."""
    try:
        return int(field)
    except ValueError:
        raise InputError(f"{name}: {field!r} is not an integer", path, line) from None


def parse_row(
    fields: Sequence[str], names: Sequence[str], path: Path, line: int
) -> list[float]:
    """Finite floats for ``fields`` (one name per field, used in messages)."""
    return [parse_float(f, path, line, n) for f, n in zip(fields, names)]


def check_increasing(times: Sequence[float] | np.ndarray, lines: Sequence[int], path: Path) -> None:
    """Raise InputError at the first row whose timestamp is not after the previous one."""
    t = np.asarray(times)
    if t.size < 2:
        return
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicate" if t[i] == t[i - 1] else "unsorted"
        raise InputError(
            f"{kind} timestamp {t[i]!r} (previous row, line {lines[i - 1]}, has {t[i - 1]!r}); "
            "timestamps must be strictly increasing",
            path,
            lines[i],
        )


def normalise_quaternion(q: Sequence[float], path: Path, line: int) -> np.ndarray:
    """Unit quaternion from ``q`` (any component order); |q| must be within
    :data:`QUAT_NORM_TOL` of 1."""
    arr = np.asarray(q, dtype=np.float64)
    norm = float(np.linalg.norm(arr))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise InputError(f"quaternion norm {norm:.6g} is not 1", path, line)
    return arr / norm


def format_float(value: float) -> str:
    """Shortest text that reads back to exactly ``value``."""
    return repr(float(value))
