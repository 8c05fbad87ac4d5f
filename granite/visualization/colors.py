"""The fixed colour map for landmarks (paper Fig. 1a).

Inverse distance ``d`` (1/m, or 1/map-unit for monocular runs) is clipped to ``[0, d_max]`` and
mapped along five stops: blue (far, small ``d``) -> cyan -> green -> yellow -> red (near,
``d = d_max``). Points at infinity (``d == 0`` exactly) are magenta, and tracks that are not
(yet) landmarks are grey, so both stay visibly distinct from far finite points.
"""

from __future__ import annotations

import numpy as np

_STOPS = np.array(
    [[0, 64, 255], [0, 220, 255], [40, 220, 40], [255, 230, 0], [255, 30, 0]], dtype=np.float64
)
INFINITY_COLOR = np.array([230, 0, 230], dtype=np.uint8)
UNMAPPED_COLOR = np.array([150, 150, 150], dtype=np.uint8)


def inverse_distance_colors(inverse_distance: np.ndarray, d_max: float = 1.0) -> np.ndarray:
    """RGB colours (N, 3) uint8 for inverse distances; NaN marks tracks without a landmark."""
    d = np.asarray(inverse_distance, dtype=np.float64)
    x = np.clip(np.nan_to_num(d, nan=0.0) / d_max, 0.0, 1.0) * (len(_STOPS) - 1)
    i = np.minimum(x.astype(int), len(_STOPS) - 2)
    f = (x - i)[:, None]
    colors = np.round((1 - f) * _STOPS[i] + f * _STOPS[i + 1]).astype(np.uint8)
    colors[d == 0.0] = INFINITY_COLOR
    colors[np.isnan(d)] = UNMAPPED_COLOR
    return colors
