"""The estimator's state machine: every transition and the frame status it reports."""

import pytest

from granite.estimator.tracking_state import FrameStatus, MapState, next_state

E, R, M = MapState.EMPTY, MapState.ROTATION_ONLY, MapState.MAPPED


@pytest.mark.parametrize("state, initialized, lost, expected", [
    (E, False, False, (R, FrameStatus.INIT)),        # first frame of a sub-map
    (R, False, False, (R, FrameStatus.INIT)),        # still rotation only
    (R, True, False, (M, FrameStatus.TRACKING)),     # first map
    (M, False, False, (M, FrameStatus.TRACKING)),
    (M, True, False, (M, FrameStatus.REINIT)),       # map lost and initialised again
    (R, False, True, (E, FrameStatus.LOST)),
    (M, False, True, (E, FrameStatus.LOST)),
    (M, True, True, (E, FrameStatus.LOST)),          # a failure overrides an initialisation
])
def test_transitions(state, initialized, lost, expected):
    assert next_state(state, initialized=initialized, lost=lost) == expected


def test_status_values_are_the_diagnostics_labels():
    assert {s.value for s in FrameStatus} == {"skipped", "init", "tracking", "reinit", "lost"}
