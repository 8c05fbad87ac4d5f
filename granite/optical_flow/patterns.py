"""Sampling patterns of the tracked patches.

The 52-point pattern is a diamond of samples on a 2 px lattice at odd offsets
``±1, ±3, ±5, ±7`` (rows of 4, 6, 8, 8, 8, 8, 6, 4 samples), spanning ±7 px, as in the
reference implementation; it is scaled (default 0.75, so ±5.25 px). Offsets are (x, y) in
pixels of the level the patch is sampled on.

``gridN`` is an N x N square lattice over the same extent (±7 px before scaling; spacing
14 / (N - 1) px): more samples per patch, so less image noise in the estimate (ours; the
reference uses the 52-point diamond, see ``docs/optical_flow.md``). With the scale
``(N - 1) / 14`` its spacing is one pixel (``grid11`` at ``5 / 7``: ±5 px); offsets within
1e-9 px of a multiple of 0.5 px are then rounded to it, so the samples of a patch lie exactly one
pixel apart and share their bilinear weights (the tracker's fast template path,
:func:`granite.optical_flow.patch.unit_lattice_side`).
"""

from __future__ import annotations

import numpy as np

#: Half-widths of the 8 rows of the diamond, from y = +7 down to y = -7.
_ROW_HALF_WIDTHS = {7: 3, 5: 5, 3: 7, 1: 7, -1: 7, -3: 7, -5: 5, -7: 3}


def pattern52_raw() -> np.ndarray:
    """The unscaled 52-point diamond, shape (52, 2), float64, (x, y) offsets."""
    points = [
        (float(x), float(y))
        for y, half in _ROW_HALF_WIDTHS.items()
        for x in range(-half, half + 1, 2)
    ]
    out = np.asarray(points, dtype=np.float64)
    assert out.shape == (52, 2)
    return out


def pattern52(scale: float = 0.75) -> np.ndarray:
    """The 52-point pattern scaled by ``scale``, shape (52, 2), float64, C-contiguous."""
    return np.ascontiguousarray(pattern52_raw() * float(scale))


#: Pattern names accepted by :func:`make_pattern` (``[optical_flow] pattern``).
PATTERN_NAMES = ("pattern52", "grid7", "grid9", "grid11", "grid13")


def grid_pattern(n: int, scale: float = 0.75) -> np.ndarray:
    """An ``n`` x ``n`` square lattice spanning ±7 px, scaled by ``scale``: shape (n*n, 2),
    float64, (x, y) offsets, rows from y = +7 down as the diamond."""
    if n < 2:
        raise ValueError(f"grid pattern: n must be at least 2, got {n}")
    g = np.linspace(-7.0, 7.0, n) * float(scale)
    half = np.round(2.0 * g) / 2.0
    g = np.where(np.abs(g - half) < _SNAP_PX, half, g)
    yy, xx = np.meshgrid(g[::-1], g, indexing="ij")
    return np.ascontiguousarray(np.column_stack([xx.ravel(), yy.ravel()]))


#: Lattice offsets this close to a multiple of 0.5 px are snapped to it [px].
_SNAP_PX = 1e-9


def pattern_size(name: str) -> int:
    """Number of samples of the pattern called ``name`` (one of :data:`PATTERN_NAMES`)."""
    return 52 if name == "pattern52" else int(name[4:]) ** 2


def make_pattern(name: str, scale: float = 0.75) -> np.ndarray:
    """The pattern called ``name`` (one of :data:`PATTERN_NAMES`), scaled by ``scale``."""
    if name == "pattern52":
        return pattern52(scale)
    if name.startswith("grid") and name in PATTERN_NAMES:
        return grid_pattern(int(name[4:]), scale)
    raise ValueError(f"unknown pattern {name!r}; known: {', '.join(PATTERN_NAMES)}")
