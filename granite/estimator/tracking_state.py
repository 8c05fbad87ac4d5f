"""The estimator's state machine (paper Sec. IV-C, Fig. 2b).

A sub-map is :class:`MapState` ``EMPTY`` until its first frame, ``ROTATION_ONLY`` while every
landmark is at infinity (the VO tracks rotation only and attempts a two-view map initialisation
every frame), and ``MAPPED`` once an initialisation has given finite landmarks and the scale
fix. A tracking failure empties it (restart); the lost frame itself then starts the new
sub-map at the identity (``MonocularVO`` moves it to ``ROTATION_ONLY``), as the reference does. Every processed frame gets a :class:`FrameStatus`, the ``state`` column of
``diagnostics.csv``. All transitions are in :func:`next_state`.
"""

from __future__ import annotations

import enum


class MapState(enum.Enum):
    """What the current sub-map has."""

    EMPTY = "empty"
    ROTATION_ONLY = "rotation_only"
    MAPPED = "mapped"


class FrameStatus(enum.Enum):
    """What happened to a frame (value: the diagnostics label)."""

    #: no usable image (missing, unreadable or rejected by the frontend): the last pose repeats
    SKIPPED = "skipped"
    #: no map yet: rotation-only tracking, map initialisation attempted
    INIT = "init"
    #: tracked against the map (also the frame that initialised the first map)
    TRACKING = "tracking"
    #: the map was lost (too few finite landmarks) and initialised again in this frame
    REINIT = "reinit"
    #: tracking failure: the window restarts and the next frame starts a new sub-map
    LOST = "lost"


def next_state(state: MapState, *, initialized: bool, lost: bool) -> tuple[MapState, FrameStatus]:
    """The sub-map's state after a processed frame, and that frame's status.

    ``initialized``: a two-view map initialisation succeeded in this frame; ``lost``: the
    tracking-failure test fired (too few connected landmarks or a diverged optimisation).
    """
    if lost:
        return MapState.EMPTY, FrameStatus.LOST
    if state is MapState.MAPPED:
        return MapState.MAPPED, FrameStatus.REINIT if initialized else FrameStatus.TRACKING
    if initialized:
        return MapState.MAPPED, FrameStatus.TRACKING
    return MapState.ROTATION_ONLY, FrameStatus.INIT
