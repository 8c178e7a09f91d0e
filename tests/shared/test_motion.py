"""The motion models and the clock that times them."""

from __future__ import annotations

import math

import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.motion import UNORDERED_KEPT, Prediction, ScanClock, fused


def test_a_clock_whose_stamps_agree_with_the_motion_is_trusted_and_times_by_its_stamps() -> None:
    clock = ScanClock(max_speed=2.0)
    for k in range(10):
        clock.tick(0.2 * k)
        assert clock.check(0.2, 0.3, 0.01)  # 1.5 m/s
    assert clock.trusted and clock.elapsed(0.37, 2) == 0.37
    assert clock.period == pytest.approx(0.2)


def test_motion_no_robot_drives_in_the_stamps_interval_distrusts_the_stamps_for_good() -> None:
    clock = ScanClock(max_speed=2.0)
    for stamp in (0.0, 0.2, 0.4, 0.401, 0.6, 0.8):
        clock.tick(stamp)
    assert not clock.check(0.001, 0.3, 0.01), "0.3 m in 1 ms"
    assert clock.too_fast == 1 and clock.distrusted_at == 6
    # from now on the time between scans is their count times the log's mean period
    assert clock.elapsed(0.001, 1) == pytest.approx(0.16)
    assert clock.elapsed(0.5, 3) == pytest.approx(0.48)
    assert not clock.check(0.2, 0.1, 0.01), "distrusted for the rest of the log"


def test_motion_within_the_registrations_own_uncertainty_does_not_distrust() -> None:
    clock = ScanClock(max_speed=1.0)
    clock.tick(0.0)
    clock.tick(0.1)
    assert clock.check(0.1, 0.12, 0.02), "0.02 m beyond 1 m/s, uncertain by 0.02 m: one sigma"
    assert not clock.check(0.1, 0.2, 0.02), "five sigma"


def test_a_repeated_or_backward_stamp_untimes_the_intervals_it_bounds_and_a_log_without_times_runs_per_scan() -> None:
    clock = ScanClock(max_speed=1.0)
    for stamp in (5.0, 5.2, 5.4, 5.6):
        clock.tick(stamp)
    clock.tick(5.6)  # scan 5: no laser takes two scans at one instant
    clock.tick(5.9)
    clock.tick(6.1)
    assert clock.trusted, "the other stamps still time their intervals"
    assert clock.elapsed(0.2, 1, 4) == pytest.approx(0.2), "scans 3-4: before the repeat"
    assert clock.elapsed(1e-9, 1, 5) == pytest.approx(clock.period), "scans 4-5: the repeat ends it"
    assert clock.elapsed(0.3, 1, 6) == pytest.approx(clock.period), "scans 5-6: the repeat begins it"
    assert clock.elapsed(0.5, 2, 7) == pytest.approx(2 * clock.period), "scans 5-7"
    assert clock.elapsed(0.2, 1, 7) == pytest.approx(0.2), "scans 6-7: after it"
    clock.tick(6.0)
    assert (clock.repeated, clock.backwards) == (1, 1) and not clock.times(1)
    flat = ScanClock(max_speed=1.0)
    for _ in range(4):
        flat.tick(0.0)
    assert flat.period == 1.0 and flat.elapsed(0.0, 2) == 2.0


def test_a_scan_that_arrived_in_a_burst_untimes_its_intervals_and_a_clock_remembers_a_bounded_span() -> None:
    clock = ScanClock(max_speed=1.0)
    for stamp in (0.0, 0.2):
        clock.tick(stamp)
    clock.bunched(2)  # scans 3 and 4 arrive stamped together
    clock.tick(0.6)
    clock.bunched(2)
    clock.tick(0.601)
    clock.tick(0.8)
    assert clock.trusted and clock.bunches == 2
    assert clock.elapsed(0.2, 1, 2) == pytest.approx(0.2)
    assert not clock.times(1, 3) and not clock.times(1, 5) and clock.times(1, 2)
    for k in range(UNORDERED_KEPT + 10):  # a log in bursts for days: every scan marked
        clock.bunched(2)
        clock.tick(1.0 + k)
    clock.tick(UNORDERED_KEPT + 20.0)
    clock.tick(UNORDERED_KEPT + 20.2)
    assert len(clock.unordered) == UNORDERED_KEPT, "the marks a clock keeps are bounded"
    assert clock.times(1) and not clock.times(2), "the newest ones still untime what they bound"
    assert not clock.times(clock.scans - 1), "an interval reaching back past the oldest kept holds newer ones"


def test_stamps_that_advanced_once_only_time_nothing_and_two_steps_measure_the_rate() -> None:
    # csail-corrected's stamps, printed to six digits, step once by 1e4 s in 406 scans: not a
    # period of 25 s a scan
    coarse = ScanClock(max_speed=1.0)
    for k in range(406):
        coarse.tick(1.13486e9 if k < 364 else 1.13487e9)
    assert coarse.period == 1.0 and coarse.elapsed(0.0, 3) == 3.0
    # a burst's first two scans arrived together, the third a period later: two steps, a rate
    burst = ScanClock(max_speed=1.0)
    for stamp in (0.0, 0.001, 0.4):
        burst.tick(stamp)
    assert burst.period == pytest.approx(0.2)


def test_two_predictions_fuse_by_their_information() -> None:
    sure = Prediction(Transform2D(1.0, 0.0, 0.0), 0.1, 0.1, "odometry")
    loose = Prediction(Transform2D(0.0, 0.0, math.pi - 0.1), 0.3, 0.3, "velocity")
    both = fused(sure, loose)
    assert both.increment.x == pytest.approx(0.9)  # weights 100 : 11.1
    assert both.sigma_translation == pytest.approx(1 / math.sqrt(1 / 0.01 + 1 / 0.09))
    # headings near +-pi average across the cut, not through zero
    a = Prediction(Transform2D(0, 0, math.pi - 0.1), 0.1, 0.1, "a")
    wrapped = fused(a, Prediction(Transform2D(0, 0, -math.pi + 0.1), 0.1, 0.1, "b"))
    assert abs(abs(wrapped.increment.theta) - math.pi) < 1e-9
