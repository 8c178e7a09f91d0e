"""Broken clocks made on purpose: the scans as robots with bad clocks record them."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pytest
from fleetmap.scenarios.clocks import BURST_SPREAD, JITTER, NUDGE, SKEW, break_clock
from fleetmap.shared.core.geometry import Transform2D


@dataclass(frozen=True)
class Reading:
    index: int
    stamp: float
    odometry: Transform2D | None


def straight(n: int = 200, period: float = 0.2, speed: float = 1.0) -> list[Reading]:
    """A robot driving along x at ``speed``, a scan every ``period`` seconds."""
    return [Reading(k, 100.0 + period * k, Transform2D(speed * period * k, 0.0, 0.0)) for k in range(n)]


def test_bursts_stamp_groups_of_two_to_four_scans_together_and_read_the_odometry_there() -> None:
    scans = straight()
    broken = list(break_clock(scans, "burst", seed=3))
    assert [s.index for s in broken] == [s.index for s in scans]
    stamps = np.array([s.stamp for s in broken])
    assert np.all(np.diff(stamps) >= 0), "a burst arrives after the one before"
    close = np.diff(stamps) <= BURST_SPREAD
    assert 0.4 < close.mean() < 0.8, "two in three scans arrive with the one before (groups of 2-4)"
    run = 0
    for c in close:
        run = run + 1 if c else 0
        assert run <= 3, "no group holds more than 4 scans"
    for s in broken:  # the odometry is read at the broken stamp: x = speed * (stamp - start)
        assert s.odometry.x == pytest.approx(s.stamp - 100.0, abs=1e-9)
    assert all(b.stamp >= a.stamp for a, b in zip(scans, broken, strict=True)), "stamped at arrival"


def test_jitter_moves_stamps_both_ways_and_skew_moves_only_the_odometry() -> None:
    scans = straight()
    jittered = list(break_clock(scans, "jitter", seed=1))
    offsets = np.array([b.stamp - a.stamp for a, b in zip(scans, jittered, strict=True)])
    assert offsets.min() < -JITTER / 2 and offsets.max() > JITTER / 2 and np.abs(offsets).max() <= JITTER
    skewed = list(break_clock(scans, "skew"))
    assert [s.stamp for s in skewed] == [s.stamp for s in scans]
    assert skewed[10].odometry.x == pytest.approx(scans[10].odometry.x + SKEW, abs=1e-9)
    drawn = list(break_clock(scans, "skew", seed=3))  # one skew drawn again: its stamps nudged
    moved = np.array([b.stamp - a.stamp for a, b in zip(scans, drawn, strict=True)])
    assert 0 < np.abs(moved).max() <= NUDGE
    assert drawn[10].odometry.x == pytest.approx(drawn[10].stamp - 100.0 + SKEW, abs=1e-9)


def test_a_nudge_moves_each_stamp_by_at_most_a_millisecond_in_order_and_a_seed_nudges_alike() -> None:
    scans = straight()
    nudged = list(break_clock(scans, "nudge", seed=4))
    offsets = np.array([b.stamp - a.stamp for a, b in zip(scans, nudged, strict=True)])
    assert np.abs(offsets).max() <= NUDGE and offsets.min() < 0 < offsets.max()
    assert all(b.stamp > a.stamp for a, b in itertools.pairwise(nudged)), "scans 0.2 s apart stay in order"
    for a, b in zip(scans, nudged, strict=True):  # the odometry read at the nudged stamp: within a millimetre
        assert abs(b.odometry.x - a.odometry.x) <= NUDGE + 1e-9
    assert [s.stamp for s in break_clock(scans, "nudge", seed=4)] == [s.stamp for s in nudged]
    assert [s.stamp for s in break_clock(scans, "nudge", seed=5)] != [s.stamp for s in nudged]


def test_drop_loses_about_one_scan_in_ten_and_repeat_copies_stamps() -> None:
    scans = straight(1000)
    dropped = list(break_clock(scans, "drop", seed=2))
    assert 850 < len(dropped) < 950 and dropped[0] == scans[0]
    repeated = list(break_clock(scans, "repeat", seed=2))
    same = sum(b.stamp == a.stamp for a, b in itertools.pairwise(repeated))
    assert 50 < same < 150


def test_the_same_seed_breaks_the_same_way_and_the_true_clock_changes_nothing() -> None:
    scans = straight()
    assert list(break_clock(scans, "burst", seed=4)) == list(break_clock(scans, "burst", seed=4))
    assert list(break_clock(scans, "true")) == scans


def test_a_turn_through_pi_is_interpolated_the_short_way() -> None:
    scans = [Reading(k, float(k), Transform2D(0.0, 0.0, math.remainder(3.0 + 0.1 * k, math.tau))) for k in range(4)]
    skewed = list(break_clock(scans, "skew"))  # read 0.1 s later: 0.01 rad further
    assert skewed[1].odometry.theta == pytest.approx(math.remainder(3.11, math.tau), abs=1e-9)


def test_stamps_that_do_not_increase_and_unknown_clocks_are_refused() -> None:
    for stamps in ([0.0] * 5, [0.0, 1.0, 1.0, 2.0]):  # all 0; rounded
        with pytest.raises(ValueError, match="no clock to break"):
            list(break_clock([Reading(k, t, None) for k, t in enumerate(stamps)], "burst"))
    with pytest.raises(ValueError, match="unknown clock 'late'"):
        list(break_clock(straight(), "late"))
