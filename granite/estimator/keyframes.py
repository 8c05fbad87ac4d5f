"""Keyframe selection by negative entropy (paper Sec. IV-D, Eq. 10).

The negative entropy ``E = ln det(I)`` of the newest pose's Fisher information is compared with
its running average since the last keyframe. A log-determinant can be negative, so the
reference's "drops to or below ``fraction`` of the average" is applied sign-independently:
a drop is ``E <= A - (1 - fraction) * |A|``, which equals ``E <= fraction * A`` for positive
``A`` and still means "lower than the average by the same relative margin" for negative ``A``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def entropy_dropped(negative_entropy: float, running_average: float, fraction: float) -> bool:
    """True when ``negative_entropy`` fell below ``fraction`` of ``running_average``."""
    return negative_entropy <= running_average - (1.0 - fraction) * abs(running_average)


@dataclass
class EntropyKeyframeSelector:
    """Stateful keyframe criterion: feed one value per tracked frame, reset at each keyframe.

    ``update`` returns True when a keyframe should be taken: the negative entropy dropped (see
    :func:`entropy_dropped`), fewer than ``min_connected_points`` points are connected, or
    (``invalid_forces_keyframe``) the negative entropy is missing or not finite.
    Entropy drops are only acted on ``min_frames_after_keyframe`` frames after a keyframe.
    """

    fraction: float = 0.995
    min_connected_points: int = 20
    min_frames_after_keyframe: int = 3
    #: a missing or non-finite negative entropy (singular information) forces a keyframe, as
    #: in the reference (False: it is ignored)
    invalid_forces_keyframe: bool = True
    _sum: float = 0.0
    _count: int = 0

    @property
    def running_average(self) -> float | None:
        return self._sum / self._count if self._count else None

    def reset(self) -> None:
        """Start a new running average (call when a keyframe was inserted)."""
        self._sum, self._count = 0.0, 0

    def update(self, negative_entropy: float, connected_points: int) -> bool:
        if connected_points < self.min_connected_points:
            return True
        if not math.isfinite(negative_entropy):
            return self.invalid_forces_keyframe
        average = self.running_average
        drop = (
            average is not None
            and self._count >= self.min_frames_after_keyframe
            and entropy_dropped(negative_entropy, average, self.fraction)
        )
        self._sum += negative_entropy
        self._count += 1
        return drop
