"""The online correction law (service/core/robot/online_correction.py): smoothed, bounded, watched."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.robot.online_correction import APPLY, HOLD, CorrectionFilter, CorrectionLimits


def test_the_offset_is_the_deviation_undone_and_smoothed_by_the_gain():
    f = CorrectionFilter(CorrectionLimits(gain=0.5))
    first = f.update(0.00, np.array([0.4, -0.2, 0.1]), 0.01)
    assert first.state == APPLY and first.reason == ""
    np.testing.assert_allclose(first.offset_mm, [-0.4, 0.2, -0.1])  # the first frame's own
    second = f.update(0.01, np.array([0.0, 0.0, 0.3]), 0.01)
    np.testing.assert_allclose(second.offset_mm, [-0.2, 0.1, -0.2])  # half-way to the new one
    every = CorrectionFilter(CorrectionLimits(gain=1.0))
    every.update(0.0, np.array([1.0, 0.0, 0.0]), 0.0)
    np.testing.assert_allclose(every.update(0.01, np.array([0.0, 0.5, 0.0]), 0.0).offset_mm, [0.0, -0.5, 0.0])


def test_a_deviation_beyond_the_bound_holds_and_is_never_clipped():
    f = CorrectionFilter(CorrectionLimits(max_mm=1.0, max_deg=0.1))
    f.update(0.0, np.array([0.5, 0.0, 0.0]), 0.01)
    far = f.update(0.01, np.array([0.0, 1.2, 0.0]), 0.01)
    assert far.state == HOLD and far.reason == "beyond_bound" and "1.200 mm" in far.message
    np.testing.assert_array_equal(far.offset_mm, np.zeros(3))
    turned = f.update(0.02, np.array([0.1, 0.0, 0.0]), 0.05)
    assert turned.state == APPLY  # the hold reset the filter: it starts again from this frame
    np.testing.assert_allclose(turned.offset_mm, [-0.1, 0.0, 0.0])
    assert f.update(0.03, np.array([0.1, 0.0, 0.0]), 0.25).reason == "beyond_bound"  # the angle's bound


def test_frames_without_a_pose_ride_on_the_last_offset_until_the_watchdog_holds():
    f = CorrectionFilter(CorrectionLimits(watchdog_s=0.25))
    assert f.update(0.0, None, None, "the robot is disconnected").reason == "no_flange"  # nothing to keep
    f.update(1.00, np.array([0.2, 0.0, 0.0]), 0.0)
    kept = f.update(1.10, None, None, "too few targets")
    assert kept.state == APPLY
    np.testing.assert_allclose(kept.offset_mm, [-0.2, 0.0, 0.0])
    assert f.check(1.20) is None
    stale = f.update(1.30, None, None)
    assert stale.state == HOLD and stale.reason == "stale" and "300 ms" in stale.message
    assert f.check(5.0) is None  # holding already: nothing more to say
    f.update(6.0, np.array([0.1, 0.0, 0.0]), 0.0)
    late = f.check(6.3)
    assert late is not None and late.reason == "stale"
    assert f.update(6.4, np.array([np.nan, 0.0, 0.0]), 0.0).reason == "no_flange"


@pytest.mark.parametrize("bad", [{"gain": 0.0}, {"gain": 1.5}, {"max_mm": 0.0}, {"watchdog_s": -1.0}])
def test_limits_that_make_no_sense_are_refused(bad):
    with pytest.raises(ValueError):
        CorrectionLimits(**bad)
