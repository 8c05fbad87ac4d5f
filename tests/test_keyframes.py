"""Negative-entropy keyframe criterion, including its sign handling."""

import math

from granite.estimator.keyframes import EntropyKeyframeSelector, entropy_dropped


def test_drop_is_detected_for_positive_and_negative_averages():
    # Positive average 100: threshold 99.5.
    assert entropy_dropped(99.4, 100.0, 0.995)
    assert not entropy_dropped(99.6, 100.0, 0.995)
    # Negative average -100: a value *above* the average is never a drop (the naive test
    # E <= 0.995 * A would flag -99.7, which carries more information than the average).
    assert not entropy_dropped(-99.7, -100.0, 0.995)
    assert entropy_dropped(-100.6, -100.0, 0.995)
    assert not entropy_dropped(-100.4, -100.0, 0.995)


def test_selector_waits_for_history_and_resets():
    sel = EntropyKeyframeSelector(fraction=0.9, min_connected_points=20, min_frames_after_keyframe=3)
    values = [10.0, 10.0, 10.0]
    assert [sel.update(v, 100) for v in values] == [False, False, False]
    assert sel.running_average == 10.0
    assert not sel.update(9.5, 100)  # within 10 % of the average
    assert sel.update(8.0, 100)  # below 0.9 * average (9.875 after the previous frame)
    sel.reset()
    assert sel.running_average is None
    assert not sel.update(1.0, 100)  # no history yet: no decision
    assert sel.update(50.0, 5)  # too few connected points forces a keyframe
    assert sel.update(math.nan, 100)  # a singular or missing entropy forces one (reference)
    assert sel.update(-math.inf, 100)
    assert sel.running_average == 1.0  # and does not enter the average
    quiet = EntropyKeyframeSelector(fraction=0.9, invalid_forces_keyframe=False)
    assert not quiet.update(math.nan, 100)
    assert not quiet.update(-math.inf, 100)
