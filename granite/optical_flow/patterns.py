"""Sparse sampling patterns of the tracked patches.

The 52-point pattern is a diamond of samples on a 2 px lattice at odd offsets
``±1, ±3, ±5, ±7`` (rows of 4, 6, 8, 8, 8, 8, 6, 4 samples), spanning ±7 px, as in the
reference implementation; it is scaled (default 0.75, so ±5.25 px). Offsets are (x, y) in
pixels of the level the patch is sampled on.
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
